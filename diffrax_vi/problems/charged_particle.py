"""A charged particle gyrating in a non-uniform, axisymmetric magnetic field (planar)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["charged_particle"]


class _Field(eqx.Module):
    """The vector potential `A(q) = f(r²) (−y, x)` with `f(s) = B₀ (1/2 + κ s/4)`."""

    b0: float = eqx.field(static=True)
    kappa: float = eqx.field(static=True)

    def potential(self, q):
        f = self.b0 * (0.5 + 0.25 * self.kappa * jnp.sum(q**2))
        return f * jnp.stack([-q[1], q[0]])


class _Lagrangian(_Field):
    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(v**2) + jnp.sum(self.potential(q) * v)


class _Velocity(_Field):
    def __call__(self, t, q, p, args):
        return p - self.potential(q)


class _Hamiltonian(_Field):
    def __call__(self, t, q, p, args):
        return 0.5 * jnp.sum((p - self.potential(q)) ** 2)


class _AngularMomentum(eqx.Module):
    """The canonical angular momentum `x p_y − y p_x` (rotations leave `L` unchanged)."""

    def __call__(self, t, q, p, args):
        return q[0] * p[1] - q[1] * p[0]


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, b0: float, kappa: float):
        self.b0, self.kappa = b0, kappa

    def __call__(self, y: np.ndarray) -> np.ndarray:
        x, z, px, pz = (y[..., i] for i in range(4))  # z: the second coordinate
        f = self.b0 * (0.5 + 0.25 * self.kappa * (x * x + z * z))
        df = 0.25 * self.b0 * self.kappa  # f'(s), s = r²
        vx, vz = px + f * z, pz - f * x
        # ṗ = ∂(A·v)/∂q at fixed v
        fx = -2 * x * z * df * vx + (f + 2 * x * x * df) * vz
        fz = -(f + 2 * z * z * df) * vx + 2 * x * z * df * vz
        return np.stack([vx, vz, fx, fz], axis=-1)


def charged_particle(
    b0: float = 4.0,
    kappa: float = 1.0,
    q0=(1.0, 0.0),
    v0=(0.0, 1.0),
    *,
    t0: float = 0.0,
    t1: float = 100.0,
    dt: float = 0.05,
    dtype=None,
) -> Problem:
    """A unit charge of unit mass moving in the plane through the axisymmetric magnetic field
    `B_z(r) = B₀ (1 + κ r²)`.

    `L = |v|²/2 + A(q)·v` with the vector potential `A(q) = B₀ (1/2 + κ r²/4) (−y, x)`
    (`∂_x A_y − ∂_y A_x = B_z`). The momentum is not the velocity: `ϑ = v + A(q)`, the velocity
    map `v = p − A(q)`, the energy `H = |p − A(q)|²/2 = |v|²/2`, and Hamilton's equations give
    the Lorentz force `v̇ = (v_y, −v_x) B_z`. Two invariants (`problem.invariants`): the energy
    and the canonical angular momentum `x p_y − y p_x = x v_y − y v_x + r² B₀ (1/2 + κ r²/4)`.

    With the defaults (`B₀ = 4`, `κ = 1`, start at `q₀ = (1, 0)` with velocity `(0, 1)`) the
    particle gyrates on a Larmor radius `|v|/B ≈ 0.11` about a guiding centre at `r ≈ 1.11`
    (so `1 ≤ r ≤ 1.22`), in the field `B ≈ 8.9`: gyration period `2π/B ≈ 0.70`. The guiding
    centre drifts around the axis (grad-B drift, speed `|v|² |∇B|/(2B²) ≈ 0.056`) in about 126
    time units: the default span `(0, 100)` holds about 143 gyrations and 0.8 of a drift
    revolution. Energy `H₀ = 0.5`, angular momentum `4`.

    The reference of the default problem is stored with the package over `(0, 100)`
    (extended-precision computation, `problems.stored`, verified to about 1e-15 in the max
    norm); other settings or times use scipy's DOP853. No counterpart exists in the reference
    package.

    **Arguments:**

    - `b0`: the field on the axis, `B₀ > 0`.
    - `kappa`: the radial growth `κ ≥ 0` of the field (`κ = 0`: a uniform field, pure gyration).
    - `q0`: the initial position.
    - `v0`: the initial velocity; the initial momentum is `p₀ = v₀ + A(q₀)`.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"charged_particle"`.
    """
    dtype = resolve_dtype(dtype)
    b0, kappa = float(b0), float(kappa)
    if not (math.isfinite(b0) and b0 > 0):
        raise ValueError(f"b0 must be positive and finite; got {b0}")
    if not (math.isfinite(kappa) and kappa >= 0):
        raise ValueError(f"kappa must be non-negative and finite; got {kappa}")
    q0v = as_vector(q0, 2, "q0")
    v0v = as_vector(v0, 2, "v0")
    f0 = b0 * (0.5 + 0.25 * kappa * float(q0v @ q0v))
    p0v = v0v + f0 * np.array([-q0v[1], q0v[0]])
    hamiltonian = _Hamiltonian(b0, kappa)
    return Problem(
        name="charged_particle",
        term=LagrangianTerm(_Lagrangian(b0, kappa), velocity=_Velocity(b0, kappa)),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"b0": b0, "kappa": kappa},
        hamiltonian=hamiltonian,
        reference_flow=StoredFlow(
            "charged_particle", _RHS(b0, kappa), np.concatenate([q0v, p0v]), np.array([b0, kappa])
        ),
        reference_method="stored",
        invariants={"energy": hamiltonian, "angular_momentum": _AngularMomentum()},
    )
