"""The planar double pendulum (regular, two degrees of freedom, chaotic)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["double_pendulum"]


class _Params(eqx.Module):
    l1: float = eqx.field(static=True)
    l2: float = eqx.field(static=True)
    m1: float = eqx.field(static=True)
    m2: float = eqx.field(static=True)
    g: float = eqx.field(static=True)


class _Lagrangian(_Params):
    def __call__(self, t, q, v, args):
        l1, l2, m1, m2, g = self.l1, self.l2, self.m1, self.m2, self.g
        kinetic = (
            0.5 * (m1 + m2) * l1**2 * v[0] ** 2
            + 0.5 * m2 * l2**2 * v[1] ** 2
            + m2 * l1 * l2 * v[0] * v[1] * jnp.cos(q[0] - q[1])
        )
        return kinetic + (m1 + m2) * g * l1 * jnp.cos(q[0]) + m2 * g * l2 * jnp.cos(q[1])


class _Velocity(_Params):
    def __call__(self, t, q, p, args):
        l1, l2, m1, m2 = self.l1, self.l2, self.m1, self.m2
        delta = q[0] - q[1]
        c = jnp.cos(delta)
        den = m1 + m2 * jnp.sin(delta) ** 2
        v1 = (l2 * p[0] - l1 * p[1] * c) / (l1**2 * l2 * den)
        v2 = ((m1 + m2) * l1 * p[1] - m2 * l2 * p[0] * c) / (m2 * l1 * l2**2 * den)
        return jnp.stack([v1, v2])


class _Hamiltonian(_Params):
    def __call__(self, t, q, p, args):
        l1, l2, m1, m2, g = self.l1, self.l2, self.m1, self.m2, self.g
        delta = q[0] - q[1]
        num = (
            0.5 * (m1 + m2) * l1**2 * p[1] ** 2
            + 0.5 * m2 * l2**2 * p[0] ** 2
            - m2 * l1 * l2 * p[0] * p[1] * jnp.cos(delta)
        )
        den = m2 * l1**2 * l2**2 * (m1 + m2 * jnp.sin(delta) ** 2)
        return num / den - g * (m1 + m2) * l1 * jnp.cos(q[0]) - g * m2 * l2 * jnp.cos(q[1])


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, l1: float, l2: float, m1: float, m2: float, g: float):
        self.l1, self.l2, self.m1, self.m2, self.g = l1, l2, m1, m2, g

    def __call__(self, y: np.ndarray) -> np.ndarray:
        l1, l2, m1, m2, g = self.l1, self.l2, self.m1, self.m2, self.g
        q1, q2, p1, p2 = (y[..., i] for i in range(4))
        delta = q1 - q2
        c, s = np.cos(delta), np.sin(delta)
        den = m1 + m2 * s**2
        v1 = (l2 * p1 - l1 * p2 * c) / (l1**2 * l2 * den)
        v2 = ((m1 + m2) * l1 * p2 - m2 * l2 * p1 * c) / (m2 * l1 * l2**2 * den)
        coupling = m2 * l1 * l2 * v1 * v2 * s
        f1 = -coupling - (m1 + m2) * g * l1 * np.sin(q1)
        f2 = coupling - m2 * g * l2 * np.sin(q2)
        return np.stack([v1, v2, f1, f2], axis=-1)


def double_pendulum(
    l=(2.0, 3.0),  # noqa: E741 - the rod lengths, named as in the reference
    m=(1.0, 2.0),
    g: float = 9.80665,
    q0=(math.pi / 4, math.pi / 2),
    v0=(0.0, math.pi / 8),
    p0=None,
    *,
    t0: float = 0.0,
    t1: float = 10.0,
    dt: float = 0.01,
    dtype=None,
) -> Problem:
    """The planar double pendulum, angles measured from the downward vertical.

    `L = (m₁+m₂) l₁² v₁²/2 + m₂ l₂² v₂²/2 + m₂ l₁ l₂ v₁ v₂ cos(q₁−q₂) + (m₁+m₂) g l₁ cos q₁
    + m₂ g l₂ cos q₂`. With `Δ = q₁ − q₂` and `d = m₁ + m₂ sin²Δ`, the term carries the
    closed-form inverse Legendre map

    - `v₁ = (l₂ p₁ − l₁ p₂ cos Δ) / (l₁² l₂ d)`,
    - `v₂ = ((m₁+m₂) l₁ p₂ − m₂ l₂ p₁ cos Δ) / (m₂ l₁ l₂² d)`,

    and the energy is
    `H = [(m₁+m₂) l₁² p₂²/2 + m₂ l₂² p₁²/2 − m₂ l₁ l₂ p₁ p₂ cos Δ] / (m₂ l₁² l₂² d)
    − (m₁+m₂) g l₁ cos q₁ − m₂ g l₂ cos q₂` (`H₀ = −40.218179175435154` for the defaults). The
    initial momentum is `p₀ = ϑ(q₀, v₀) = (3.3321622036187746, 7.0685834705770345)` by default.
    The reference solution of the default problem is stored with the package over
    `(t0, t0 + 10)` (extended-precision computation, verified to 3e-14 in the max
    norm); other settings or times use scipy's DOP853 of Hamilton's equations. The motion is
    chaotic: beyond `t ≈ 10` no reference is good to many digits.

    The reference package's default span is `(0, 10)` with step `0.01`; its benchmark uses
    `(0, 10 dt)` instead (see `Problem.with_span`).

    **Arguments:**

    - `l`, `m`: the two rod lengths and bob masses (positive).
    - `g`: gravity.
    - `q0`, `v0`: the initial angles and angular velocities.
    - `p0`: the initial momenta; default `ϑ(q0, v0)`. If given, `v0` is ignored.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"double_pendulum"`.
    """
    dtype = resolve_dtype(dtype)
    l1, l2 = (float(x) for x in as_vector(l, 2, "l"))
    m1, m2 = (float(x) for x in as_vector(m, 2, "m"))
    g = float(g)
    if not (l1 > 0 and l2 > 0 and m1 > 0 and m2 > 0):
        raise ValueError(f"lengths and masses must be positive; got l={l}, m={m}")
    params = (l1, l2, m1, m2, g)
    q0v = as_vector(q0, 2, "q0")
    if p0 is None:
        v0v = as_vector(v0, 2, "v0")
        c = math.cos(q0v[0] - q0v[1])
        p0v = np.array(
            [
                (m1 + m2) * l1**2 * v0v[0] + m2 * l1 * l2 * v0v[1] * c,
                m2 * l2**2 * v0v[1] + m2 * l1 * l2 * v0v[0] * c,
            ]
        )
    else:
        p0v = as_vector(p0, 2, "p0")

    return Problem(
        name="double_pendulum",
        term=LagrangianTerm(_Lagrangian(*params), velocity=_Velocity(*params)),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"l1": l1, "l2": l2, "m1": m1, "m2": m2, "g": g},
        hamiltonian=_Hamiltonian(*params),
        reference_flow=StoredFlow(
            "double_pendulum", _RHS(*params), np.concatenate([q0v, p0v]), np.array(params)
        ),
        reference_method="stored",
    )
