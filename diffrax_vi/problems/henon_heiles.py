"""The Hénon–Heiles system (regular, two degrees of freedom)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["henon_heiles"]


def _potential(q, lam):
    return 0.5 * jnp.sum(q**2) + lam * (q[0] ** 2 * q[1] - q[1] ** 3 / 3)


class _Lagrangian(eqx.Module):
    lam: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(v**2) - _potential(q, self.lam)


class _Velocity(eqx.Module):
    def __call__(self, t, q, p, args):
        return p


class _Hamiltonian(eqx.Module):
    lam: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return 0.5 * jnp.sum(p**2) + _potential(q, self.lam)


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, lam: float):
        self.lam = lam

    def __call__(self, y: np.ndarray) -> np.ndarray:
        q1, q2, p1, p2 = (y[..., i] for i in range(4))
        lam = self.lam
        f1 = -q1 - 2 * lam * q1 * q2
        f2 = -q2 - lam * (q1**2 - q2**2)
        return np.stack([p1, p2, f1, f2], axis=-1)


def henon_heiles(
    lam: float = 1.0,
    q0=(0.2, 0.2),
    p0=(0.3, 0.3),
    *,
    t0: float = 0.0,
    t1: float = 10.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """The Hénon–Heiles system `L = |v|²/2 − |q|²/2 − λ (q₁² q₂ − q₂³/3)`.

    Momentum `ϑ = v`, force `f = −(q₁ + 2λ q₁ q₂, q₂ + λ (q₁² − q₂²))`, energy
    `H = |p|²/2 + |q|²/2 + λ (q₁² q₂ − q₂³/3)` (`H₀ = 0.13533333333333333` for the defaults;
    the VISE documentation uses `q₀ = p₀ = (0.1, 0.1)` with `H₀ = 0.0206667`). The motion stays
    bounded for `H < 1/(6λ²)`.

    The reference solution of the default problem is stored with the package over
    `(t0, t0 + 10)` (extended-precision computation, verified to 8e-16 in the max norm); other
    settings or times use scipy's DOP853.

    **Arguments:**

    - `lam`: the strength `λ` of the cubic term.
    - `q0`, `p0`: the initial positions and momenta.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"henon_heiles"`.
    """
    dtype = resolve_dtype(dtype)
    lam = float(lam)
    if not np.isfinite(lam):
        raise ValueError(f"lam must be finite; got {lam}")
    q0v = as_vector(q0, 2, "q0")
    p0v = as_vector(p0, 2, "p0")
    hamiltonian = _Hamiltonian(lam)
    return Problem(
        name="henon_heiles",
        term=LagrangianTerm(_Lagrangian(lam), velocity=_Velocity()),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"lam": lam},
        hamiltonian=hamiltonian,
        reference_flow=StoredFlow(
            "henon_heiles", _RHS(lam), np.concatenate([q0v, p0v]), np.array([lam])
        ),
        reference_method="stored",
        invariants={"energy": hamiltonian},
    )
