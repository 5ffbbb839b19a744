"""The Fermi–Pasta–Ulam chain of stiff and soft springs (fast/slow, adiabatic invariant)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["fermi_pasta_ulam"]


def _soft_stretches(x0, x1, xp):
    """The elongations of the `m + 1` soft springs, times √2: `x₀₁ − x₁₁`,
    `x₀,ᵢ₊₁ − x₁,ᵢ₊₁ − x₀ᵢ − x₁ᵢ`, `−(x₀ₘ + x₁ₘ)` (`xp`: `jax.numpy` or `numpy`). Spring `k`
    holds `−(x₀ₖ + x₁ₖ)` of the stiff spring on its left and `x₀,ₖ₊₁ − x₁,ₖ₊₁` of the one
    on its right (zero-based), which is the chain rule `_RHS` uses."""
    inner = x0[..., 1:] - x1[..., 1:] - x0[..., :-1] - x1[..., :-1]
    return xp.concatenate(
        [x0[..., :1] - x1[..., :1], inner, -(x0[..., -1:] + x1[..., -1:])], axis=-1
    )


class _Params(eqx.Module):
    m: int = eqx.field(static=True)
    omega: float = eqx.field(static=True)

    def potential(self, q):
        x0, x1 = q[: self.m], q[self.m :]
        stiff = 0.5 * self.omega**2 * jnp.sum(x1**2)
        return stiff + 0.25 * jnp.sum(_soft_stretches(x0, x1, jnp) ** 4)


class _Lagrangian(_Params):
    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(v**2) - self.potential(q)


class _Velocity(eqx.Module):
    def __call__(self, t, q, p, args):
        return p


class _Hamiltonian(_Params):
    def __call__(self, t, q, p, args):
        return 0.5 * jnp.sum(p**2) + self.potential(q)


class _OscillatoryEnergies(_Params):
    """`I_j = (y₁ⱼ² + ω² x₁ⱼ²)/2`, one per stiff spring (shape `(m,)`)."""

    def __call__(self, t, q, p, args):
        return 0.5 * (p[self.m :] ** 2 + self.omega**2 * q[self.m :] ** 2)


class _OscillatoryEnergy(_Params):
    """`I = I₁ + … + I_m`, the total energy of the stiff springs."""

    def __call__(self, t, q, p, args):
        return 0.5 * jnp.sum(p[self.m :] ** 2 + self.omega**2 * q[self.m :] ** 2)


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, m: int, omega: float):
        self.m, self.omega = m, omega

    def __call__(self, y: np.ndarray) -> np.ndarray:
        m = self.m
        x0, x1, p = y[..., :m], y[..., m : 2 * m], y[..., 2 * m :]
        g = _soft_stretches(x0, x1, np) ** 3  # d(s⁴/4)/ds of the springs 0..m
        # stiff spring j enters soft spring j as (+x₀ⱼ − x₁ⱼ) and soft spring j+1 as −(x₀ⱼ + x₁ⱼ)
        f0 = -(g[..., :m] - g[..., 1:])
        f1 = -(-g[..., :m] - g[..., 1:]) - self.omega**2 * x1
        return np.concatenate([p, f0, f1], axis=-1)


def fermi_pasta_ulam(
    m: int = 3,
    omega: float = 50.0,
    q0=None,
    p0=None,
    *,
    t0: float = 0.0,
    t1: float = 200.0,
    dt: float = 0.01,
    dtype=None,
) -> Problem:
    """The Fermi–Pasta–Ulam problem of Hairer, Lubich & Wanner (*Geometric Numerical
    Integration*, §I.5): `2m` unit masses in a chain with fixed ends, joined alternately by soft
    quartic springs and stiff linear springs of frequency `ω`.

    The coordinates are those of the book: for each stiff spring `j = 1 … m` the displacement
    of its centre `x₀ⱼ` and its elongation `x₁ⱼ` (both scaled by `1/√2`), `q = (x₀₁ … x₀ₘ,
    x₁₁ … x₁ₘ)`, momenta `p = v`. The Lagrangian is `L = |v|²/2 − U(q)` with
    `U = ω²/2 Σⱼ x₁ⱼ² + 1/4 [(x₀₁ − x₁₁)⁴ + Σⱼ₌₁^{m−1} (x₀,ⱼ₊₁ − x₁,ⱼ₊₁ − x₀ⱼ − x₁ⱼ)⁴
    + (x₀ₘ + x₁ₘ)⁴]`, energy `H = |p|²/2 + U`.

    The default data are the book's: `m = 3`, `ω = 50`, `x₀₁ = 1`, `y₀₁ = 1`, `x₁₁ = 1/ω`,
    `y₁₁ = 1`, the rest zero (`H₀ ≈ 2.0`). Time scales: the stiff springs oscillate with period
    `2π/ω ≈ 0.126`, the soft motion on a scale of order 1, and the stiff springs exchange energy
    on the scale `ω` (about 50); the default span `(0, 200)` holds some 1600 fast periods.

    Invariants (`problem.invariants`): the energy `"energy"` (exact), the oscillatory energy
    `"oscillatory_energy"` `I = I₁ + … + I_m` and the individual `"oscillatory_energies"`
    `Iⱼ = (y₁ⱼ² + ω² x₁ⱼ²)/2` (an array of shape `(m,)`). `I` is an adiabatic invariant: it is
    only approximately conserved, `I(t) = I(0) + O(1/ω)` over exponentially long times
    (`I₀ = 1`; along the default reference it stays within 0.063 of 1), while the `Iⱼ`
    exchange energy among themselves (`I₃` exceeds 0.95 near `t = 150`).

    The reference of the default problem is stored with the package over `(0, 200)`
    (extended-precision computation, `problems.stored`; the float64 hops between checkpoints
    are verified to 4e-14 in the max norm); other settings or times use scipy's DOP853. The
    slow motion is chaotic: a perturbation of `x₀₁` by 1e-12 grows to 3e-6 by `t = 200`
    (about 200-fold by `t = 50`). So the checkpoints themselves carry the amplified rounding of
    the extended-precision run: two such runs with 32 and 64 steps per checkpoint spacing differ
    by 2e-11 at the end of the span. Over the first half of the span the reference is good to
    about 1e-13, at its end to about 2e-11 — still far below a float64 solver's own rounding,
    which the same growth amplifies. No counterpart exists in the reference package.

    **Arguments:**

    - `m`: the number of stiff springs, an integer `≥ 1`.
    - `omega`: the stiff springs' frequency `ω > 0`.
    - `q0`, `p0`: initial `(x₀, x₁)` and `(y₀, y₁)` (`2m` components each); default the book's.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"fermi_pasta_ulam"`.
    """
    dtype = resolve_dtype(dtype)
    if isinstance(m, bool) or not isinstance(m, int | np.integer) or m < 1:
        raise ValueError(f"m, the number of stiff springs, must be an integer >= 1; got {m!r}")
    m = int(m)
    omega = float(omega)
    if not (math.isfinite(omega) and omega > 0):
        raise ValueError(f"omega must be positive and finite; got {omega}")
    if q0 is None:
        q0v = np.zeros(2 * m)
        q0v[0], q0v[m] = 1.0, 1.0 / omega
    else:
        q0v = as_vector(q0, 2 * m, "q0")
    if p0 is None:
        p0v = np.zeros(2 * m)
        p0v[0], p0v[m] = 1.0, 1.0
    else:
        p0v = as_vector(p0, 2 * m, "p0")
    hamiltonian = _Hamiltonian(m, omega)
    return Problem(
        name="fermi_pasta_ulam",
        term=LagrangianTerm(_Lagrangian(m, omega), velocity=_Velocity()),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"m": m, "omega": omega},
        hamiltonian=hamiltonian,
        reference_flow=StoredFlow(
            "fermi_pasta_ulam",
            _RHS(m, omega),
            np.concatenate([q0v, p0v]),
            np.array([m, omega], dtype=np.float64),
        ),
        reference_method="stored",
        invariants={
            "energy": hamiltonian,
            "oscillatory_energy": _OscillatoryEnergy(m, omega),
            "oscillatory_energies": _OscillatoryEnergies(m, omega),
        },
    )
