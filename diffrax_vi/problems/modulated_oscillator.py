"""A harmonic oscillator with a slowly modulated frequency (time-dependent, adiabatic)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["modulated_oscillator"]


class _Params(eqx.Module):
    omega0: float = eqx.field(static=True)
    epsilon: float = eqx.field(static=True)
    nu: float = eqx.field(static=True)

    def omega(self, t):
        return self.omega0 * (1 + self.epsilon * jnp.sin(self.nu * t))


class _Lagrangian(_Params):
    def __call__(self, t, q, v, args):
        return jnp.sum(0.5 * v**2 - 0.5 * self.omega(t) ** 2 * q**2)


class _Velocity(eqx.Module):
    def __call__(self, t, q, p, args):
        return p


class _Hamiltonian(_Params):
    def __call__(self, t, q, p, args):
        return jnp.sum(0.5 * p**2 + 0.5 * self.omega(t) ** 2 * q**2)


class _AdiabaticInvariant(_Params):
    """`J = H/ω`: the action of the frozen oscillator, `(1/2π) ∮ p dq`."""

    def __call__(self, t, q, p, args):
        w = self.omega(t)
        return jnp.sum(0.5 * p**2 / w + 0.5 * w * q**2)


class _RHS:
    """Hamilton's equations on the augmented state `(q, p, t)`, NumPy, any float dtype."""

    def __init__(self, omega0: float, epsilon: float, nu: float):
        self.omega0, self.epsilon, self.nu = omega0, epsilon, nu

    def __call__(self, y: np.ndarray) -> np.ndarray:
        if y.shape[-1] != 3:
            raise ValueError(
                "the modulated oscillator is time-dependent: its field acts on (q, p, t), "
                f"got a state of {y.shape[-1]} components"
            )
        q, p, t = y[..., :1], y[..., 1:2], y[..., 2:]
        w = self.omega0 * (1 + self.epsilon * np.sin(self.nu * t))
        return np.concatenate([p, -(w**2) * q, np.ones_like(t)], axis=-1)


def modulated_oscillator(
    omega0: float = 1.0,
    epsilon: float = 0.5,
    nu: float = 0.1,
    q0: float = 1.0,
    p0: float = 0.0,
    *,
    t0: float = 0.0,
    t1: float = 200.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """A harmonic oscillator whose frequency is modulated slowly in time.

    `L = v²/2 − ω(t)² q²/2` with `ω(t) = ω₀ (1 + ε sin(ν t))`, `ν ≪ ω₀`: the Lagrangian depends
    on `t` explicitly. Momentum `ϑ = v`, energy `H(t, q, p) = p²/2 + ω(t)² q²/2`, which is **not**
    conserved: `dH/dt = ∂H/∂t = ω ω̇ q²`. For the defaults (`ω₀ = 1`, `ε = 0.5`, `ν = 0.1`) the
    frequency swings between 0.5 and 1.5: the fast period is `2π/ω ≈ 4.2 … 12.6`, the
    modulation period `2π/ν ≈ 62.8`, and the default span `(0, 200)` holds about 32 fast
    oscillations and 3.2 modulation periods.

    The invariant of interest is the adiabatic invariant `J = H/ω(t)` (`problem.invariants`:
    `"adiabatic_invariant"`; `J₀ = 0.5` for the defaults). It is only approximately conserved:
    it oscillates by a relative amount of order `ε ν/ω₀` without a secular drift (along the
    default reference `J` stays within 0.480 … 0.522, while the energy swings between 0.25 and
    0.75). The energy is `problem.energy`, not an invariant.

    The reference of the default problem (with `t0 = 0`) is stored with the package over
    `(0, 200)`: the augmented autonomous system in `(q, p, t)` integrated in extended precision
    (`problems.stored`, verified to about 1e-15 in the max norm). Another start time,
    parameters, initial data or times outside the span use scipy's DOP853 on the same augmented
    system. No counterpart exists in the reference package.

    **Arguments:**

    - `omega0`: the mean frequency `ω₀ > 0`.
    - `epsilon`: the relative modulation depth `ε`, `0 ≤ ε < 1` (so that `ω > 0`).
    - `nu`: the modulation frequency `ν ≥ 0`.
    - `q0`, `p0`: the initial position and momentum.
    - `t0`, `t1`, `dt`: the default span and step (the reference depends on `t0` too).
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"modulated_oscillator"`.
    """
    dtype = resolve_dtype(dtype)
    omega0, epsilon, nu = float(omega0), float(epsilon), float(nu)
    if not (math.isfinite(omega0) and omega0 > 0):
        raise ValueError(f"omega0 must be positive and finite; got {omega0}")
    if not (math.isfinite(epsilon) and 0 <= epsilon < 1):
        raise ValueError(
            f"epsilon must lie in [0, 1) so that the frequency stays positive; got {epsilon}"
        )
    if not (math.isfinite(nu) and nu >= 0):
        raise ValueError(f"nu must be non-negative and finite; got {nu}")
    q0v = as_vector(q0, 1, "q0")
    p0v = as_vector(p0, 1, "p0")
    params = (omega0, epsilon, nu)
    hamiltonian = _Hamiltonian(*params)
    return Problem(
        name="modulated_oscillator",
        term=LagrangianTerm(_Lagrangian(*params), velocity=_Velocity()),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"omega0": omega0, "epsilon": epsilon, "nu": nu},
        hamiltonian=hamiltonian,
        reference_flow=StoredFlow(
            "modulated_oscillator",
            _RHS(*params),
            np.concatenate([q0v, p0v]),
            np.array(params),
            t0=float(t0),
        ),
        reference_method="stored",
        invariants={"adiabatic_invariant": _AdiabaticInvariant(*params)},
    )
