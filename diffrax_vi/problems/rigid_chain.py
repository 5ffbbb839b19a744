"""A planar chain of rigid links hanging from a pivot, in Cartesian coordinates with one
length constraint per link, gravity and damped joints; its reference comes from the joint
angles."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .extended import ExtendedPrecisionFlow, spd_solve

__all__ = ["rigid_chain", "chain_angles_to_state", "JointDamping"]


def _relative(x):
    """Link vectors `r_i − r_{i−1}` (the pivot `r_0` at the origin) of stacked points."""
    return x - jnp.concatenate([jnp.zeros_like(x[:1]), x[:-1]])


class _ChainLagrangian(eqx.Module):
    """`L = Σ m_k |v_k|²/2 − Σ m_k g y_k` of point masses `q = (x_1, y_1, ..., x_N, y_N)`."""

    masses: tuple[float, ...] = eqx.field(static=True)
    g: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        m = jnp.asarray(self.masses, q.dtype)
        r, w = q.reshape(-1, 2), v.reshape(-1, 2)
        return 0.5 * jnp.sum(m * jnp.sum(w * w, axis=1)) - self.g * jnp.sum(m * r[:, 1])


class _LinkLengths(eqx.Module):
    """`g_i(q) = (|r_i − r_{i−1}|² − ℓ_i²) / 2`, one per link."""

    lengths: tuple[float, ...] = eqx.field(static=True)

    def __call__(self, t, q, args):
        d = _relative(q.reshape(-1, 2))
        return 0.5 * (jnp.sum(d * d, axis=1) - jnp.asarray(self.lengths, q.dtype) ** 2)


class JointDamping(eqx.Module):
    """The damping torques of the joints, `F = −∂R/∂v` of the dissipation
    `R = (c/2) Σ_i (ω_i − ω_{i−1})²`, `ω_i` the angular velocity of link `i` (`ω_0 = 0`, the
    first joint damps against the fixed pivot).

    `damping` is an ordinary (differentiable) field: `eqx.tree_at` swaps in a traced value."""

    damping: ArrayLike

    def __call__(self, t, q, v, args):
        d, w = _relative(q.reshape(-1, 2)), _relative(v.reshape(-1, 2))
        omega = (d[:, 0] * w[:, 1] - d[:, 1] * w[:, 0]) / jnp.sum(d * d, axis=1)
        slip = _relative(omega[:, None])[:, 0]  # ω_i − ω_{i−1}
        torque = -jnp.asarray(self.damping, q.dtype) * (
            slip - jnp.concatenate([slip[1:], jnp.zeros_like(slip[:1])])
        )
        # The torque τ_i on the angle of link i as a force on the points: ∂ω_i/∂v_k.
        per_link = torque[:, None] * jnp.stack([-d[:, 1], d[:, 0]], axis=1) / jnp.sum(
            d * d, axis=1
        )[:, None]
        force = per_link - jnp.concatenate([per_link[1:], jnp.zeros_like(per_link[:1])])
        return force.reshape(-1)


class _ChainEnergy(eqx.Module):
    masses: tuple[float, ...] = eqx.field(static=True)
    g: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        m = jnp.asarray(self.masses, q.dtype)
        r, mom = q.reshape(-1, 2), p.reshape(-1, 2)
        return jnp.sum(jnp.sum(mom * mom, axis=1) / (2 * m)) + self.g * jnp.sum(m * r[:, 1])


class _AngleField:
    """`(θ, θ̇)'` of the chain in its joint angles (`θ_i` of link `i` from the downward
    vertical): `M(θ) θ̈ = −C(θ, θ̇) − ∂V/∂θ + Q(θ̇)`, NumPy only (runs in `np.longdouble`)."""

    def __init__(self, masses, lengths, g, damping):
        m = np.asarray(masses, np.float64)
        self.tail = np.cumsum(m[::-1])[::-1]  # μ_i = Σ_{k ≥ i} m_k
        self.lengths = np.asarray(lengths, np.float64)
        self.g, self.damping = g, damping

    def __call__(self, y):
        n = self.lengths.shape[0]
        dt = y.dtype.type
        theta, omega = y[..., :n], y[..., n:]
        ell = self.lengths.astype(dt)
        idx = np.arange(n)
        mu = self.tail.astype(dt)[np.maximum(idx[:, None], idx[None, :])]
        diff = theta[..., :, None] - theta[..., None, :]
        lij = ell[:, None] * ell[None, :]
        mass = mu * lij * np.cos(diff)
        coriolis = np.sum(mu * lij * np.sin(diff) * omega[..., None, :] ** 2, axis=-1)
        gravity = dt(self.g) * self.tail.astype(dt) * ell * np.sin(theta)
        slip = omega - np.concatenate([np.zeros_like(omega[..., :1]), omega[..., :-1]], axis=-1)
        ahead = np.concatenate([slip[..., 1:], np.zeros_like(slip[..., :1])], axis=-1)
        torque = -dt(self.damping) * (slip - ahead)
        accel = spd_solve(mass, torque - coriolis - gravity)
        return np.concatenate([omega, accel], axis=-1)


def chain_angles_to_state(masses, lengths, angles, rates) -> tuple[np.ndarray, np.ndarray]:
    """`(q, p)` of the chain from joint angles and their rates (rows `(..., N)`), NumPy in
    the inputs' dtype: `r_k = Σ_{i≤k} ℓ_i (sin θ_i, −cos θ_i)`, `p_k = m_k ṙ_k`."""
    angles, rates = np.asarray(angles), np.asarray(rates)
    ell = np.asarray(lengths, np.float64).astype(angles.dtype)
    m = np.asarray(masses, np.float64).astype(angles.dtype)
    s, c = np.sin(angles), np.cos(angles)
    r = np.stack([np.cumsum(ell * s, axis=-1), np.cumsum(-ell * c, axis=-1)], axis=-1)
    v = np.stack(
        [np.cumsum(ell * rates * c, axis=-1), np.cumsum(ell * rates * s, axis=-1)], axis=-1
    )
    q = r.reshape(*r.shape[:-2], -1)
    p = (m[:, None] * v).reshape(*v.shape[:-2], -1)
    return q, p


def rigid_chain(
    n_links: int = 5,
    damping: float = 0.05,
    angles: ArrayLike | None = None,
    rates: ArrayLike | None = None,
    *,
    mass: float = 1.0,
    length: float = 1.0,
    g: float = 9.81,
    t0: float = 0.0,
    t1: float = 10.0,
    dt: float = 0.02,
    dtype=None,
) -> Problem:
    """A planar chain of `n_links` rigid massless links of `length`, hanging from a fixed
    pivot, with a point `mass` at the end of each link; in Cartesian coordinates
    `q = (x_1, y_1, ..., x_N, y_N)` with the `N` holonomic constraints
    `(|r_i − r_{i−1}|² − ℓ²)/2 = 0` and the joint damping `JointDamping(damping)` (a torque
    `−c(ω_i − ω_{i−1})` at each joint, against the pivot at the first).

    The start is given by the joint angles from the downward vertical (default
    `0.4 + 0.1 i`, released from rest) and their rates. The reference integrates the chain
    in those angles in extended precision and maps it to `(q, p)`. Without damping the
    energy is conserved; with it, it falls.

    **Returns:** a `Problem` named `"rigid_chain"`.
    """
    dtype = resolve_dtype(dtype)
    if not isinstance(n_links, int) or n_links < 1:
        raise ValueError(f"n_links must be a positive int, got {n_links!r}")
    mass, length, g, damping = float(mass), float(length), float(g), float(damping)
    if not (mass > 0 and length > 0 and g >= 0 and damping >= 0):
        raise ValueError(
            f"need mass > 0, length > 0, g >= 0, damping >= 0; got mass={mass}, "
            f"length={length}, g={g}, damping={damping}"
        )
    theta = (
        0.4 + 0.1 * np.arange(n_links)
        if angles is None
        else as_vector(angles, n_links, "angles")
    )
    omega = np.zeros(n_links) if rates is None else as_vector(rates, n_links, "rates")
    masses, lengths = (mass,) * n_links, (length,) * n_links
    q0, p0 = chain_angles_to_state(masses, lengths, theta, omega)

    def to_state(y):
        return chain_angles_to_state(masses, lengths, y[..., :n_links], y[..., n_links:])

    return Problem(
        name="rigid_chain",
        term=LagrangianTerm(
            _ChainLagrangian(masses, g),
            force=JointDamping(damping),
            constraint=_LinkLengths(lengths),
        ),
        y0=make_state(q0, p0, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"n_links": n_links, "mass": mass, "length": length, "g": g, "damping": damping},
        hamiltonian=_ChainEnergy(masses, g),
        reference_flow=ExtendedPrecisionFlow(
            _AngleField(masses, lengths, g, damping),
            np.concatenate([theta, omega]),
            to_state,
            steps_per_unit=60.0,
        ),
        reference_method="extended precision (joint angles)",
    )
