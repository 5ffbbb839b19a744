"""The harmonic oscillator `L = m v²/2 − k q²/2` (regular, one degree of freedom)."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import ClosedFormFlow, Problem, as_vector, make_state, resolve_dtype

__all__ = ["harmonic_oscillator"]


class OscillatorLagrangian(eqx.Module):
    m: float = eqx.field(static=True)
    k: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        return jnp.sum(0.5 * self.m * v**2 - 0.5 * self.k * q**2)


class OscillatorVelocity(eqx.Module):
    m: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return p / self.m


class OscillatorHamiltonian(eqx.Module):
    m: float = eqx.field(static=True)
    k: float = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return jnp.sum(p**2 / (2 * self.m) + 0.5 * self.k * q**2)


def harmonic_oscillator(
    m: float = 1.0,
    k: float = 0.5,
    q0: float = 0.5,
    p0: float = 0.0,
    *,
    t0: float = 0.0,
    t1: float = 1.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """The harmonic oscillator with Lagrangian `L(q, v) = m v²/2 − k q²/2`.

    Momentum `ϑ = m v`, force `f = −k q`, energy `H = p²/(2m) + k q²/2` (`H₀ = 0.0625` for the
    defaults), angular frequency `ω = √(k/m)`. The reference is the exact solution
    `q(t) = q₀ cos ωτ + p₀/(mω) sin ωτ`, `p(t) = p₀ cos ωτ − m ω q₀ sin ωτ` with `τ = t − t₀`
    (for the defaults `q(t) = 0.5 cos(t/√2)`). The term carries the closed-form velocity `p/m`.

    **Arguments:**

    - `m`, `k`: mass and spring constant (positive).
    - `q0`, `p0`: initial position and momentum; scalars, or equal-length vectors for several
      identical uncoupled oscillators.
    - `t0`, `t1`, `dt`: the default span and step.
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"harmonic_oscillator"`.
    """
    dtype = resolve_dtype(dtype)
    m, k = float(m), float(k)
    if not (m > 0 and k > 0):
        raise ValueError(f"m and k must be positive; got m={m}, k={k}")
    q0v = as_vector(q0, None, "q0")
    p0v = as_vector(p0, q0v.shape[0], "p0")
    omega = math.sqrt(k / m)

    def solution(tau):
        c = np.cos(omega * tau)[:, None]
        s = np.sin(omega * tau)[:, None]
        q = q0v * c + p0v / (m * omega) * s
        p = p0v * c - m * omega * q0v * s
        return q, p

    return Problem(
        name="harmonic_oscillator",
        term=LagrangianTerm(OscillatorLagrangian(m, k), velocity=OscillatorVelocity(m)),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"m": m, "k": k},
        hamiltonian=OscillatorHamiltonian(m, k),
        reference_flow=ClosedFormFlow(solution),
        reference_method="closed form",
    )
