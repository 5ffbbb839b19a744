"""The damped and driven oscillator `m q̈ = −k q − c q̇ + A cos(Ω t)`: a Lagrangian with a
non-conservative force, and its closed-form solution."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import ClosedFormFlow, Problem, as_vector, make_state, resolve_dtype
from .harmonic_oscillator import OscillatorHamiltonian, OscillatorLagrangian, OscillatorVelocity

__all__ = ["damped_oscillator", "driven_oscillator", "forced_oscillator"]


class _Force(eqx.Module):
    """`F(t, q, v) = −c v + A cos(Ω t)`."""

    damping: float = eqx.field(static=True)
    amplitude: float = eqx.field(static=True)
    frequency: float = eqx.field(static=True)

    def __call__(self, t, q, v, args):
        drive = self.amplitude * jnp.cos(self.frequency * t)
        return -self.damping * v + jnp.asarray(drive, v.dtype)


def forced_oscillator(
    m: float = 1.0,
    k: float = 1.0,
    damping: float = 0.1,
    amplitude: float = 0.0,
    frequency: float = 0.0,
    q0: float = 1.0,
    p0: float = 0.0,
    *,
    t0: float = 0.0,
    t1: float = 10.0,
    dt: float = 0.1,
    dtype=None,
) -> Problem:
    """The oscillator `L = m v²/2 − k q²/2` with the non-conservative force
    `F(t, q, v) = −c v + A cos(Ω t)` (`c` the damping, `A` and `Ω` the drive).

    The reference is the closed-form solution: the steady response
    `Re(A e^{iΩt} / (k − mΩ² + icΩ))` plus the free motion `e^{−γτ}(C₁ cos ω_d τ +
    C₂ sin ω_d τ)` that meets the initial state, with `γ = c/(2m)`,
    `ω_d = √(k/m − γ²)`. The energy `H = p²/(2m) + k q²/2` is not conserved: the force's
    power `F·v` changes it.

    **Arguments:**

    - `m`, `k`: mass and spring constant (positive); `damping`: `c ≥ 0`, below critical
      (`c² < 4mk`).
    - `amplitude`, `frequency`: the drive `A cos(Ω t)` (`Ω ≥ 0`); off resonance where
      `c = 0` (`Ω ≠ √(k/m)`).
    - `q0`, `p0`: initial position and momentum (`p = m v`); scalars, or equal-length
      vectors for several uncoupled oscillators.
    - `t0`, `t1`, `dt`: the default span and step; `dtype`: the floating dtype of `y0`.

    **Returns:** a `Problem` named `"forced_oscillator"`.
    """
    dtype = resolve_dtype(dtype)
    m, k, c = float(m), float(k), float(damping)
    a, big_omega = float(amplitude), float(frequency)
    if not (m > 0 and k > 0):
        raise ValueError(f"m and k must be positive; got m={m}, k={k}")
    if not (0 <= c and c * c < 4 * m * k):
        raise ValueError(f"damping must be in [0, 2√(mk)) (under-damped); got {c}")
    if big_omega < 0:
        raise ValueError(f"frequency must be non-negative; got {big_omega}")
    response = k - m * big_omega**2 + 1j * c * big_omega
    if a != 0 and abs(response) < 1e-12 * k:
        raise ValueError("the drive is at resonance without damping: no bounded solution")
    q0v = as_vector(q0, None, "q0")
    p0v = as_vector(p0, q0v.shape[0], "p0")
    gamma = c / (2 * m)
    omega_d = math.sqrt(k / m - gamma**2)
    start = float(t0)
    steady = a / response if a != 0 else 0j

    def forced(t):  # the steady response and its velocity at times t
        phase = np.exp(1j * big_omega * np.asarray(t, np.float64))
        return np.real(steady * phase), np.real(1j * big_omega * steady * phase)

    qs0, vs0 = forced(start)
    c1 = q0v - qs0
    c2 = (p0v / m - vs0 + gamma * c1) / omega_d

    def solution(tau):
        tau = np.asarray(tau, np.float64)
        decay = np.exp(-gamma * tau)[:, None]
        cos, sin = np.cos(omega_d * tau)[:, None], np.sin(omega_d * tau)[:, None]
        q_free = decay * (c1 * cos + c2 * sin)
        v_free = decay * ((c2 * omega_d - gamma * c1) * cos - (c1 * omega_d + gamma * c2) * sin)
        qs, vs = forced(start + tau)
        return q_free + qs[:, None], m * (v_free + vs[:, None])

    return Problem(
        name="forced_oscillator",
        term=LagrangianTerm(OscillatorLagrangian(m, k), velocity=OscillatorVelocity(m),
                            force=_Force(c, a, big_omega)),
        y0=make_state(q0v, p0v, dtype),
        t0=start,
        t1=float(t1),
        dt=float(dt),
        params={"m": m, "k": k, "damping": c, "amplitude": a, "frequency": big_omega},
        hamiltonian=OscillatorHamiltonian(m, k),
        reference_flow=ClosedFormFlow(solution),
        reference_method="closed form",
    )


def damped_oscillator(m: float = 1.0, k: float = 1.0, damping: float = 0.1, **kwargs) -> Problem:
    """`forced_oscillator` without a drive: `m q̈ = −k q − c q̇`, decaying as `e^{−ct/(2m)}`."""
    return forced_oscillator(m, k, damping, 0.0, 0.0, **kwargs)


def driven_oscillator(
    m: float = 1.0, k: float = 1.0, amplitude: float = 0.5, frequency: float = 0.7,
    damping: float = 0.0, **kwargs
) -> Problem:
    """`forced_oscillator` driven by `A cos(Ω t)` (undamped by default, off resonance)."""
    return forced_oscillator(m, k, damping, amplitude, frequency, **kwargs)


