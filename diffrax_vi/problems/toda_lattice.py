"""The periodic Toda lattice (regular, `N` degrees of freedom, integrable)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["toda_lattice", "bump_initial_condition"]


def _potential(q, alpha):
    return alpha * jnp.sum(jnp.exp(q - jnp.roll(q, -1)))


class _Lagrangian(eqx.Module):
    alpha: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(v**2) - _potential(q, self.alpha)


class _Velocity(eqx.Module):
    def __call__(self, t, q, p, args):
        return p


class _Hamiltonian(eqx.Module):
    alpha: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return 0.5 * jnp.sum(p**2) + _potential(q, self.alpha)


class _TotalMomentum(eqx.Module):
    def __call__(self, t, q, p, args):
        return jnp.sum(p)


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, n: int, alpha: float):
        self.n, self.alpha = n, alpha

    def __call__(self, y: np.ndarray) -> np.ndarray:
        q, p = y[..., : self.n], y[..., self.n :]
        e = self.alpha * np.exp(q - np.roll(q, -1, axis=-1))  # α E_j, E_j = exp(q_j − q_{j+1})
        force = np.roll(e, 1, axis=-1) - e  # −∂V/∂q_j = α (E_{j−1} − E_j)
        return np.concatenate([p, force], axis=-1)


def _spline(x: np.ndarray) -> np.ndarray:
    x = np.abs(x)
    inner = 1 - 1.5 * x**2 + 0.75 * x**3
    outer = 0.25 * (2 - x) ** 3
    return np.where(x <= 1, inner, np.where(x <= 2, outer, 0.0))


def bump_initial_condition(n: int, mu: float = 0.3) -> np.ndarray:
    """The reference's "bump" positions: `h(20 μ |ξ + μ/2|)` on `n` points `ξ` of `[−½, ½]`.

    `h` is the cubic B-spline-like profile `1 − 3x²/2 + 3x³/4` on `[0, 1]`, `(2 − x)³/4` on
    `(1, 2]` and zero beyond.
    """
    xi = np.linspace(-0.5, 0.5, n)
    return _spline(20 * mu * np.abs(xi + mu / 2))


def toda_lattice(
    n: int = 16,
    alpha: float = 0.64,
    mu: float = 0.3,
    q0=None,
    p0=None,
    *,
    t0: float = 0.0,
    t1: float = 120.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """The periodic Toda lattice `L = |v|²/2 − α Σₙ exp(qₙ − qₙ₊₁)`, with `q_{N+1} ≡ q₁`.

    Momentum `ϑ = v`, energy `H = |p|²/2 + α Σₙ exp(qₙ − qₙ₊₁)`; besides the energy, the total
    momentum `Σₙ pₙ` is conserved (both are in `problem.invariants`, as `"energy"` and
    `"momentum"`). The default initial state is the reference's bump (`bump_initial_condition`,
    `μ = 0.3`) at rest; for `N = 16` its energy is `H₀ = 10.423704531565422`.

    The reference solution of the default problem (`N = 16`, `α = 0.64`, `μ = 0.3`) is stored
    with the package over `(t0, t0 + 120)` (extended-precision computation, verified to about
    1.4e-15 in the max norm, see `problems.stored`); other settings or times use scipy's DOP853.
    The reference package's default size is `N = 200`; its benchmark uses `N = 16`.

    **Arguments:**

    - `n`: the number of particles `N ≥ 2`.
    - `alpha`: the coupling `α > 0`.
    - `mu`: the width parameter of the bump (`0 < μ`).
    - `q0`, `p0`: initial positions and momenta (`N` components each); default the bump and
      zero momenta.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"toda_lattice"`.
    """
    dtype = resolve_dtype(dtype)
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 2:
        raise ValueError(f"the lattice needs an integer number of particles n >= 2; got {n!r}")
    n = int(n)
    alpha, mu = float(alpha), float(mu)
    if not alpha > 0:
        raise ValueError(f"alpha must be positive; got {alpha}")
    if not mu > 0:
        raise ValueError(f"mu must be positive; got {mu}")
    q0v = bump_initial_condition(n, mu) if q0 is None else as_vector(q0, n, "q0")
    p0v = np.zeros(n) if p0 is None else as_vector(p0, n, "p0")
    hamiltonian = _Hamiltonian(alpha)
    key = np.array([n, alpha, mu], dtype=np.float64)
    return Problem(
        name="toda_lattice",
        term=LagrangianTerm(_Lagrangian(alpha), velocity=_Velocity()),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"n": n, "alpha": alpha, "mu": mu},
        hamiltonian=hamiltonian,
        reference_flow=StoredFlow("toda_lattice", _RHS(n, alpha), np.concatenate([q0v, p0v]), key),
        reference_method="stored",
        invariants={"energy": hamiltonian, "momentum": _TotalMomentum()},
    )
