"""The perturbed pendulum (regular, one degree of freedom, non-separable Hamiltonian)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["perturbed_pendulum"]


class _Params(eqx.Module):
    omega: float = eqx.field(static=True)
    a: float = eqx.field(static=True)


class _Lagrangian(_Params):
    def __call__(self, t, q, v, args):
        w2, a = self.omega**2, self.a
        return jnp.sum(0.5 * v**2 + w2 * jnp.cos(q) + a * q * v + 0.5 * a**2 * q**2)


class _Velocity(_Params):
    def __call__(self, t, q, p, args):
        return p - self.a * q


class _Hamiltonian(_Params):
    def __call__(self, t, q, p, args):
        return jnp.sum(0.5 * p**2 - self.omega**2 * jnp.cos(q) - self.a * q * p)


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, omega: float, a: float):
        self.w2, self.a = omega**2, a

    def __call__(self, y: np.ndarray) -> np.ndarray:
        q, p = y[..., :1], y[..., 1:]
        return np.concatenate([p - self.a * q, -self.w2 * np.sin(q) + self.a * p], axis=-1)


def perturbed_pendulum(
    omega: float = 0.5,
    epsilon: float = 0.5,
    phi: float = math.pi / 3,
    q0: float = 0.5,
    p0: float = 0.0,
    *,
    t0: float = 0.0,
    t1: float = 10.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """The reference's perturbed pendulum, with a Hamiltonian that mixes `q` and `p`.

    With `A = 0.3 ε sin 2φ + 0.7 ε sin 3φ` (`A = 0.12990381056766578` for the defaults),
    `L = v²/2 + ω² cos q + A q v + A² q²/2`, momentum `ϑ = v + A q`, velocity `v = p − A q` and
    energy `H = p²/2 − ω² cos q − A q p` (`H₀ = −0.21939564047259319` for the defaults).
    Hamilton's equations are `q̇ = p − A q`, `ṗ = −ω² sin q + A p`.

    The reference solution of the default problem is stored with the package over
    `(t0, t0 + 10)` (extended-precision computation, verified to 5e-16 in the max norm); other
    settings or times use scipy's DOP853.

    **Arguments:**

    - `omega`: the frequency `ω` of the unperturbed pendulum.
    - `epsilon`, `phi`: the perturbation strength `ε` and phase `φ` defining `A`.
    - `q0`, `p0`: the initial angle and momentum.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"perturbed_pendulum"`.
    """
    dtype = resolve_dtype(dtype)
    omega, epsilon, phi = float(omega), float(epsilon), float(phi)
    for name, x in (("omega", omega), ("epsilon", epsilon), ("phi", phi)):
        if not math.isfinite(x):
            raise ValueError(f"{name} must be finite; got {x}")
    a = 0.3 * epsilon * math.sin(2 * phi) + 0.7 * epsilon * math.sin(3 * phi)
    q0v = as_vector(q0, 1, "q0")
    p0v = as_vector(p0, 1, "p0")
    hamiltonian = _Hamiltonian(omega, a)
    return Problem(
        name="perturbed_pendulum",
        term=LagrangianTerm(_Lagrangian(omega, a), velocity=_Velocity(omega, a)),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"omega": omega, "epsilon": epsilon, "phi": phi, "A": a},
        hamiltonian=hamiltonian,
        reference_flow=StoredFlow(
            "perturbed_pendulum",
            _RHS(omega, a),
            np.concatenate([q0v, p0v]),
            np.array([omega, epsilon, phi]),
        ),
        reference_method="stored",
        invariants={"energy": hamiltonian},
    )
