"""The spherical pendulum in Cartesian coordinates: a point mass on a sphere, held there by a
holonomic constraint; its reference comes from the angle coordinates."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, make_state, resolve_dtype
from .extended import ExtendedPrecisionFlow

__all__ = ["spherical_pendulum"]


class _PointInGravity(eqx.Module):
    """`L = m|v|²/2 − m g z`."""

    m: float = eqx.field(static=True)
    g: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        return 0.5 * self.m * jnp.sum(v * v) - self.m * self.g * q[2]


class _OnSphere(eqx.Module):
    """`g(q) = (|q|² − ℓ²) / 2`."""

    length: float = eqx.field(static=True)

    def __call__(self, t, q, args):
        return 0.5 * (jnp.sum(q * q) - self.length**2)[None]


class _Energy(eqx.Module):
    m: float = eqx.field(static=True)
    g: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return jnp.sum(p * p) / (2 * self.m) + self.m * self.g * q[2]


class _AngleField:
    """`(θ, φ, θ̇, φ̇)' ` of the pendulum in spherical angles (`θ` from the downward vertical)."""

    def __init__(self, g_over_l: float):
        self.g_over_l = g_over_l

    def __call__(self, y):
        theta, _, dtheta, dphi = (y[..., i] for i in range(4))
        s, c = np.sin(theta), np.cos(theta)
        ddtheta = s * c * dphi**2 - self.g_over_l * s
        ddphi = -2 * c / s * dtheta * dphi
        return np.stack([dtheta, dphi, ddtheta, ddphi], axis=-1)


class _ToCartesian:
    def __init__(self, m: float, length: float):
        self.m, self.length = m, length

    def __call__(self, y):
        theta, phi, dtheta, dphi = (y[..., i] for i in range(4))
        st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
        q = self.length * np.stack([st * cp, st * sp, -ct], axis=-1)
        v = self.length * np.stack(
            [ct * cp * dtheta - st * sp * dphi, ct * sp * dtheta + st * cp * dphi, st * dtheta],
            axis=-1,
        )
        return q, self.m * v


def spherical_pendulum(
    m: float = 1.0,
    g: float = 9.81,
    length: float = 1.0,
    theta0: float = 1.0,
    phi0: float = 0.0,
    dtheta0: float = 0.0,
    dphi0: float = 2.0,
    *,
    t0: float = 0.0,
    t1: float = 10.0,
    dt: float = 0.05,
    dtype=None,
) -> Problem:
    """A mass `m` on a massless rod of `length` from a fixed pivot, free to swing in every
    direction: `L = m|v|²/2 − m g z` in Cartesian `q = (x, y, z)` with the holonomic
    constraint `g(q) = (|q|² − ℓ²)/2 = 0`.

    The start is given in spherical angles, `θ` from the downward vertical and `φ` the
    azimuth, with their rates; a nonzero `dphi0` keeps the motion away from the poles,
    where the angle coordinates are singular. The reference integrates the pendulum in those
    angles (`θ̈ = sin θ cos θ φ̇² − (g/ℓ) sin θ`, `φ̈ = −2 cot θ θ̇ φ̇`) in extended precision
    and maps it to `(q, p = m v)`. Conserved: the energy and the vertical angular momentum
    `L_z = x p_y − y p_x`.

    **Returns:** a `Problem` named `"spherical_pendulum"`.
    """
    dtype = resolve_dtype(dtype)
    m, g, length = float(m), float(g), float(length)
    if not (m > 0 and length > 0 and g >= 0):
        raise ValueError(f"need m > 0, length > 0, g >= 0; got m={m}, length={length}, g={g}")
    if not 0 < theta0 < np.pi:
        raise ValueError(f"theta0 must lie strictly between the poles (0, pi); got {theta0}")
    if dphi0 == 0:
        raise ValueError("dphi0 = 0 swings through the pole, where the reference is singular")
    angles = np.array([theta0, phi0, dtheta0, dphi0], np.float64)
    to_cartesian = _ToCartesian(m, length)
    q0, p0 = to_cartesian(angles[None])
    return Problem(
        name="spherical_pendulum",
        term=LagrangianTerm(_PointInGravity(m, g), constraint=_OnSphere(length)),
        y0=make_state(q0[0], p0[0], dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"m": m, "g": g, "length": length},
        hamiltonian=_Energy(m, g),
        reference_flow=ExtendedPrecisionFlow(_AngleField(g / length), angles, to_cartesian),
        reference_method="extended precision (angle coordinates)",
        invariants={"angular_momentum_z": lambda t, q, p, args: q[0] * p[1] - q[1] * p[0]},
    )
