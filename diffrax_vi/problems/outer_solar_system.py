"""The outer solar system: the Sun and five outer bodies in three dimensions (18 DoF)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["outer_solar_system", "SOLAR_SYSTEM_BODIES"]

SOLAR_SYSTEM_BODIES = ("Sun", "Jupiter", "Saturn", "Uranus", "Neptune", "Pluto")
# Hairer, Lubich & Wanner, "Geometric Numerical Integration", §I.2.4: masses relative to the Sun
# (the Sun's includes the inner planets), positions in AU and velocities in AU/day on
# September 5, 1994, 0h00 GST, heliocentric.
GRAVITATIONAL_CONSTANT = 2.95912208286e-4
MASSES = (
    1.00000597682,
    0.000954786104043,
    0.000285583733151,
    0.0000437273164546,
    0.0000517759138449,
    1 / 1.3e8,
)
POSITIONS = (
    (0.0, 0.0, 0.0),
    (-3.5023653, -3.8169847, -1.5507963),
    (9.0755314, -3.0458353, -1.6483708),
    (8.3101420, -16.2901086, -7.2521278),
    (11.4707666, -25.7294829, -10.8169456),
    (-15.5387357, -25.2225594, -3.1902382),
)
VELOCITIES = (
    (0.0, 0.0, 0.0),
    (0.00565429, -0.00412490, -0.00190589),
    (0.00168318, 0.00483525, 0.00192462),
    (0.00354178, 0.00137102, 0.00055029),
    (0.00288930, 0.00114527, 0.00039677),
    (0.00276725, -0.00170702, -0.00136504),
)


def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.triu_indices(n, k=1)
    return i, j


class _Params(eqx.Module):
    masses: tuple[float, ...] = eqx.field(static=True)
    gravity: float = eqx.field(static=True)

    def _mass_vector(self, dtype):
        return jnp.asarray(np.repeat(self.masses, 3), dtype=dtype)

    def _potential(self, q):
        n = len(self.masses)
        i, j = _pairs(n)
        x = q.reshape(n, 3)
        gmm = jnp.asarray(
            self.gravity * np.asarray(self.masses)[i] * np.asarray(self.masses)[j], dtype=q.dtype
        )
        distance = jnp.sqrt(jnp.sum((x[i] - x[j]) ** 2, axis=-1))
        return -jnp.sum(gmm / distance)


class _Lagrangian(_Params):
    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(self._mass_vector(q.dtype) * v**2) - self._potential(q)


class _Velocity(_Params):
    def __call__(self, t, q, p, args):
        return p / self._mass_vector(p.dtype)


class _Hamiltonian(_Params):
    def __call__(self, t, q, p, args):
        return 0.5 * jnp.sum(p**2 / self._mass_vector(p.dtype)) + self._potential(q)


class _AngularMomentum(eqx.Module):
    def __call__(self, t, q, p, args):
        return jnp.sum(jnp.cross(q.reshape(-1, 3), p.reshape(-1, 3)), axis=0)


class _LinearMomentum(eqx.Module):
    def __call__(self, t, q, p, args):
        return jnp.sum(p.reshape(-1, 3), axis=0)


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, masses: tuple[float, ...], gravity: float):
        self.n = len(masses)
        self.masses = np.asarray(masses, dtype=np.float64)
        self.i, self.j = _pairs(self.n)
        self.gmm = gravity * self.masses[self.i] * self.masses[self.j]

    def __call__(self, y: np.ndarray) -> np.ndarray:
        n, i, j = self.n, self.i, self.j
        lead = y.shape[:-1]
        x = y[..., : 3 * n].reshape(*lead, n, 3)
        p = y[..., 3 * n :].reshape(*lead, n, 3)
        d = x[..., i, :] - x[..., j, :]
        r2 = np.sum(d * d, axis=-1, keepdims=True)
        pull = (self.gmm[:, None] * d) / (r2 * np.sqrt(r2))  # force on j from i; −that on i
        force = np.zeros_like(x)
        for k in range(len(i)):
            force[..., i[k], :] -= pull[..., k, :]
            force[..., j[k], :] += pull[..., k, :]
        velocity = p / self.masses[:, None].astype(y.dtype)
        return np.concatenate(
            [velocity.reshape(*lead, 3 * n), force.reshape(*lead, 3 * n)], axis=-1
        )


def outer_solar_system(
    masses=MASSES,
    q0=None,
    v0=None,
    p0=None,
    gravity: float = GRAVITATIONAL_CONSTANT,
    *,
    t0: float = 0.0,
    t1: float = 200.0,
    dt: float = 0.5,
    dtype=None,
) -> Problem:
    """The outer solar system: Sun, Jupiter, Saturn, Uranus, Neptune and Pluto in 3-D.

    `L = Σᵢ mᵢ |vᵢ|²/2 + G Σ_{i<j} mᵢ mⱼ / |qᵢ − qⱼ|`; the state stacks the bodies' Cartesian
    coordinates, `q = (x₁, y₁, z₁, x₂, ...)` (18 components), likewise `p = (mᵢ vᵢ)`. Energy
    `H = Σᵢ |pᵢ|²/(2mᵢ) − G Σ_{i<j} mᵢ mⱼ / |qᵢ − qⱼ|`; the total angular momentum `Σᵢ qᵢ × pᵢ`
    and linear momentum `Σᵢ pᵢ` are conserved too (`problem.invariants`: `"energy"`,
    `"angular_momentum"`, `"momentum"`). Units: AU, days, solar masses,
    `G = 2.95912208286e-4`. The data are Hairer–Lubich–Wanner's (GNI §I.2.4), the Sun's mass
    including the inner planets (`1.00000597682`; the reference package uses `1.0`).

    The reference solution of the default problem is stored with the package over
    `(t0, t0 + 200)` days (extended-precision computation, verified to 3.4e-15 AU in the max
    norm); other settings or times use scipy's DOP853.

    **Arguments:**

    - `masses`: the six masses (positive).
    - `q0`, `v0`: positions and velocities, 18 components each (default: the GNI data).
    - `p0`: momenta instead of `v0` (`v0` is then ignored).
    - `gravity`: the gravitational constant `G > 0`.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"outer_solar_system"`.
    """
    dtype = resolve_dtype(dtype)
    m = as_vector(masses, None, "masses")
    if m.shape[0] < 2 or not np.all(m > 0):
        raise ValueError(f"masses must hold at least two positive values; got {masses}")
    gravity = float(gravity)
    if not (math.isfinite(gravity) and gravity > 0):
        raise ValueError(f"gravity must be positive; got {gravity}")
    n = m.shape[0]
    if q0 is None and n != len(POSITIONS):
        raise ValueError(f"give q0 and v0 (or p0) for {n} bodies")
    q0v = as_vector(np.ravel(POSITIONS) if q0 is None else np.ravel(q0), 3 * n, "q0")
    if p0 is None:
        v0v = as_vector(np.ravel(VELOCITIES) if v0 is None else np.ravel(v0), 3 * n, "v0")
        p0v = np.repeat(m, 3) * v0v
    else:
        p0v = as_vector(np.ravel(p0), 3 * n, "p0")
    masses_t = tuple(float(x) for x in m)
    hamiltonian = _Hamiltonian(masses_t, gravity)
    return Problem(
        name="outer_solar_system",
        term=LagrangianTerm(_Lagrangian(masses_t, gravity), velocity=_Velocity(masses_t, gravity)),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"G": gravity, **{f"m_{k}": x for k, x in enumerate(masses_t)}},
        hamiltonian=hamiltonian,
        reference_flow=StoredFlow(
            "outer_solar_system",
            _RHS(masses_t, gravity),
            np.concatenate([q0v, p0v]),
            np.array([gravity, *masses_t]),
        ),
        reference_method="stored",
        invariants={
            "energy": hamiltonian,
            "angular_momentum": _AngularMomentum(),
            "momentum": _LinearMomentum(),
        },
    )
