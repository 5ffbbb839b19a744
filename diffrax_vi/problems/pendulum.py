"""The reference's mathematical pendulum: a degenerate (first-order) two-component IODE."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import IODETerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["pendulum"]

# θ₀ = acos(0.4) puts the energy at H₀ = 0.4 with the bob at rest.
DEFAULT_Q0 = (math.acos(0.4), 0.0)


class _Momentum(eqx.Module):
    ml2: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        return jnp.stack([self.ml2 * q[1], jnp.zeros_like(q[1])])


class _Force(eqx.Module):
    ml2: float = eqx.field(static=True)
    mgl: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        return jnp.stack([self.mgl * jnp.sin(q[0]), self.ml2 * (v[0] - q[1])])


class _Velocity(eqx.Module):
    g_over_l: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return jnp.stack([q[1], self.g_over_l * jnp.sin(q[0])])


class _Hamiltonian(eqx.Module):
    ml2: float = eqx.field(static=True)
    mgl: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return p[0] ** 2 / (2 * self.ml2) + self.mgl * jnp.cos(q[0])


class _RHS:
    """Hamilton's equations `q̇ = v̄(q, p)`, `ṗ = f(q, v̄)` in NumPy, vectorised over leading
    axes (any float dtype): `(q₂, (g/l) sin q₁, m g l sin q₁, 0)`."""

    def __init__(self, g_over_l: float, mgl: float):
        self.g_over_l, self.mgl = g_over_l, mgl

    def __call__(self, y: np.ndarray) -> np.ndarray:
        q1, q2 = y[..., 0], y[..., 1]
        s = np.sin(q1)
        return np.stack([q2, self.g_over_l * s, self.mgl * s, np.zeros_like(q1)], axis=-1)


def pendulum(
    l: float = 1.0,  # noqa: E741 - the pendulum's length, named as in the reference
    m: float = 1.0,
    g: float = 1.0,
    q0=DEFAULT_Q0,
    p0=None,
    *,
    t0: float = 0.0,
    t1: float = 1.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """The pendulum in the reference's degenerate first-order form, as an `IODETerm`.

    The state is `q = (θ, θ̇)`: the second component plays the part of the angular velocity.
    The maps are

    - momentum `ϑ(q, v) = (m l² q₂, 0)`,
    - force `f(q, v) = (m g l sin q₁, m l² (v₁ − q₂))`,
    - velocity `v̄(q, p) = (q₂, (g/l) sin q₁)`,

    i.e. the Euler–Lagrange equations of `L(q, v) = m l² q₂ v₁ − m l² q₂²/2 − m g l cos q₁`,
    which is linear in `v` (so `∂²L/∂v²` is singular and `p₂ ≡ 0` is a constraint). They
    say `θ̈ = +(g/l) sin θ`: the potential is `+m g l cos θ` (the reference's sign convention,
    stable equilibrium at `θ = π`). The energy is `H = p₁²/(2 m l²) + m g l cos q₁` (first
    components only; `H₀ = 0.4` for the defaults).

    Standard diffrax solvers integrate the term through `v̄`; the reference solves the same
    Hamilton equations `q̇ = v̄(q, p)`, `ṗ = f(q, v̄)`, so for a consistent `p₀` it returns
    `q = (θ, θ̇)` and `p = (m l² θ̇, 0)` of the solution of `θ̈ = (g/l) sin θ`. For the default
    problem it is stored with the package over `(t0, t0 + 1)` (extended-precision computation,
    verified to 2e-15 in the max norm); other settings or times use scipy's DOP853.

    **Arguments:**

    - `l`, `m`, `g`: length, mass and gravity (positive).
    - `q0`: the initial `(θ, θ̇)`; default `(acos 0.4, 0)`.
    - `p0`: the initial momenta; default `ϑ(q0) = (m l² q0₂, 0)`.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"pendulum"`.
    """
    dtype = resolve_dtype(dtype)
    l, m, g = float(l), float(m), float(g)  # noqa: E741
    if not (l > 0 and m > 0 and g > 0):
        raise ValueError(f"l, m and g must be positive; got l={l}, m={m}, g={g}")
    ml2, mgl, g_over_l = m * l**2, m * g * l, g / l
    q0v = as_vector(q0, 2, "q0")
    p0v = np.array([ml2 * q0v[1], 0.0]) if p0 is None else as_vector(p0, 2, "p0")

    return Problem(
        name="pendulum",
        term=IODETerm(
            _Momentum(ml2),
            _Force(ml2, mgl),
            velocity=_Velocity(g_over_l),
            hamiltonian=_Hamiltonian(ml2, mgl),
        ),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"l": l, "m": m, "g": g},
        hamiltonian=_Hamiltonian(ml2, mgl),
        reference_flow=StoredFlow(
            "pendulum",
            _RHS(g_over_l, mgl),
            np.concatenate([q0v, p0v]),
            np.array([l, m, g]),
        ),
        reference_method="stored",
    )
