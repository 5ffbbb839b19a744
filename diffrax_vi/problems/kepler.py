"""The planar Kepler problem with an exact reference solution."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import ClosedFormFlow, Problem, make_state, resolve_dtype

__all__ = ["kepler", "solve_kepler_equation"]


class _Lagrangian(eqx.Module):
    def __call__(self, t, q, v, args):
        return 0.5 * jnp.sum(v**2) + 1 / jnp.sqrt(jnp.sum(q**2))


class _Velocity(eqx.Module):
    def __call__(self, t, q, p, args):
        return p


class _Hamiltonian(eqx.Module):
    def __call__(self, t, q, p, args):
        return 0.5 * jnp.sum(p**2) - 1 / jnp.sqrt(jnp.sum(q**2))


class _AngularMomentum(eqx.Module):
    def __call__(self, t, q, p, args):
        return q[0] * p[1] - q[1] * p[0]


class _RungeLenz(eqx.Module):
    def __call__(self, t, q, p, args):
        ell = q[0] * p[1] - q[1] * p[0]
        r = jnp.sqrt(jnp.sum(q**2))
        return jnp.stack([p[1] * ell, -p[0] * ell]) - q / r


def solve_kepler_equation(mean_anomaly: np.ndarray, eccentricity: float) -> np.ndarray:
    """The eccentric anomaly `E` with `E − e sin E = M`, vectorised Newton in float64.

    `M` is reduced to `[−π, π)` first (the result is then shifted back by the same multiple of
    `2π`), and Newton starts from `M + 0.85 e sign(sin M)`, which converges for every `e < 1`.
    """
    mean = np.asarray(mean_anomaly, dtype=np.float64)
    e = float(eccentricity)
    turns = np.floor((mean + np.pi) / (2 * np.pi))
    m = mean - 2 * np.pi * turns
    ecc = m + 0.85 * e * np.sign(np.sin(m))
    for _ in range(100):
        step = (ecc - e * np.sin(ecc) - m) / (1 - e * np.cos(ecc))
        ecc = ecc - step
        if np.all(np.abs(step) <= 4 * np.finfo(np.float64).eps * np.maximum(1.0, np.abs(ecc))):
            break
    return ecc + 2 * np.pi * turns


def kepler(
    eccentricity: float = 0.5,
    *,
    t0: float = 0.0,
    t1: float = 10.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """The planar Kepler problem `L = |v|²/2 + 1/|q|` (unit gravitational parameter).

    The orbit starts at perihelion, `q₀ = (1 − e, 0)`, `p₀ = (0, √((1 + e)/(1 − e)))`: an ellipse
    of semi-major axis 1 and period `2π`. Energy `H = |p|²/2 − 1/|q| = −1/2`; the angular
    momentum `q₁p₂ − q₂p₁ = √(1 − e²)` and the Laplace–Runge–Lenz vector
    `(p₂ ℓ, −p₁ ℓ) − q/|q| = (e, 0)` are conserved too (`problem.invariants`: `"energy"`,
    `"angular_momentum"`, `"runge_lenz"`).

    The reference is exact: with the eccentric anomaly `E` solving Kepler's equation
    `E − e sin E = τ` (`solve_kepler_equation`, `τ = t − t₀`),
    `q = (cos E − e, √(1−e²) sin E)` and `p = (−sin E, √(1−e²) cos E) / (1 − e cos E)`.
    No counterpart exists in the reference package.

    **Arguments:**

    - `eccentricity`: `e` in `[0, 1)`.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"kepler"`.
    """
    dtype = resolve_dtype(dtype)
    e = float(eccentricity)
    if not (math.isfinite(e) and 0 <= e < 1):
        raise ValueError(f"the eccentricity must lie in [0, 1) for a bound orbit; got {e}")
    b = math.sqrt(1 - e * e)
    q0v = np.array([1 - e, 0.0])
    p0v = np.array([0.0, math.sqrt((1 + e) / (1 - e))])

    def solution(tau):
        ecc = solve_kepler_equation(tau, e)
        c, s = np.cos(ecc), np.sin(ecc)
        q = np.stack([c - e, b * s], axis=-1)
        p = np.stack([-s, b * c], axis=-1) / (1 - e * c)[:, None]
        return q, p

    hamiltonian = _Hamiltonian()
    return Problem(
        name="kepler",
        term=LagrangianTerm(_Lagrangian(), velocity=_Velocity()),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"eccentricity": e},
        hamiltonian=hamiltonian,
        reference_flow=ClosedFormFlow(solution),
        reference_method="closed form",
        invariants={
            "energy": hamiltonian,
            "angular_momentum": _AngularMomentum(),
            "runge_lenz": _RungeLenz(),
        },
    )
