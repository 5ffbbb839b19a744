"""What rounding adds to a step: the oscillator's projected step solved exactly.

For the harmonic oscillator `L = ½ m v² − ½ k q²` the projected step's equations are linear.
`exact_increments` solves them in long double for the span, weights and step size that the
float64 step used: the exact map of the same discrete Lagrangian, which is symplectic. Along
a float64 trajectory, `energy_bias` compares each step's end with that map applied to the
step's start; the mean of the energy change that rounding adds is the step's drift rate
(Brouwer's law of random rounding needs it to vanish), its spread the random walk.
`map_deviation` finds where that mean comes from: the float64 step, fitted as a linear map
along its trajectories, differs from the exact map by a fixed matrix, and the change of the
map's determinant (zero for a symplectic map) is the drift rate. `oscillator_runs` makes the
float64 trajectories of a solver and `bias_statistics` reads all of it off them.
"""

from __future__ import annotations

from typing import NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from ..problems import harmonic_oscillator

__all__ = [
    "BiasStatistics", "bias_statistics", "energy_bias", "exact_increments", "map_deviation",
    "oscillator_runs",
]

_LD = np.longdouble


def _solve(a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """`a⁻¹ rhs` in long double (NumPy's solvers stop at float64): Gaussian elimination with
    partial pivoting, every right-hand side at once."""
    a, rhs = a.copy(), rhs.copy()
    n = a.shape[0]
    for i in range(n):
        pivot = i + int(np.argmax(np.abs(a[i:, i])))
        a[[i, pivot]], rhs[[i, pivot]] = a[[pivot, i]], rhs[[pivot, i]]
        for r in range(i + 1, n):
            factor = a[r, i] / a[i, i]
            a[r, i:] -= factor * a[i, i:]
            rhs[r] -= factor * rhs[i]
    z = np.zeros_like(rhs)
    for i in reversed(range(n)):
        z[i] = (rhs[i] - a[i, i + 1 :] @ z[i + 1 :]) / a[i, i]
    return z


def exact_increments(span, weights, h: float, q0: np.ndarray, p0: np.ndarray, m: float,
                     k: float) -> tuple[np.ndarray, np.ndarray]:
    """`(Δq, Δp)` in long double of the one-coordinate oscillator's projected step
    (`VariableProjection`'s equations; a direction that is not live is pinned to zero) from
    the states `q0`, `p0` (`(N,)`), for the float64 `span` (a `ProjectedSpan`), quadrature
    `weights` and step `h`."""
    gq, gv, g0, gd = (np.asarray(a, np.float64)[0].astype(_LD)
                      for a in (span.gq, span.gv, span.g0, span.gd))
    live = np.asarray(span.live)[:, 0]
    b = np.asarray(weights, np.float64).astype(_LD)
    h, m, k = _LD(h), _LD(m), _LD(k)
    size = gq.shape[1]
    # unknowns (δc, Δp): stationarity along each direction, and continuity at τ = 0
    a = np.zeros((size + 1, size + 1), _LD)
    a[:size, :size] = (h * k * np.einsum("j,jl,jk->kl", b, gq, gq)
                       - (m / h) * np.einsum("j,jl,jk->kl", b, gv, gv))
    a[:size, size] = g0 + gd
    a[size, :size] = -g0
    q0 = np.asarray(q0, np.float64).astype(_LD)
    p0 = np.asarray(p0, np.float64).astype(_LD)
    rhs = np.zeros((size + 1, q0.shape[0]), _LD)
    rhs[:size] = -(gd[:, None] * p0[None]
                   + h * k * np.einsum("j,jk->k", b, gq)[:, None] * q0[None])
    a[:size][~live] = 0
    a[np.flatnonzero(~live), np.flatnonzero(~live)] = 1
    rhs[:size][~live] = 0
    z = _solve(a, rhs)
    return gd @ z[:size], z[size]


def energy_bias(q: np.ndarray, p: np.ndarray, span, weights, h: float, m: float,
                k: float) -> np.ndarray:
    """Per step of the float64 trajectory `q`, `p` (`(n + 1,)`), the energy change that
    rounding adds, `(E(end) − E(exact map of start)) / E₀`, in units of float64's eps."""
    def energy(q, p):
        return p**2 / (2 * _LD(m)) + _LD(k) * q**2 / 2

    q, p = (np.asarray(x, np.float64).astype(_LD) for x in (q, p))
    dq, dp = exact_increments(span, weights, h, q[:-1], p[:-1], m, k)
    e0 = energy(q[0], p[0])
    change = (energy(q[1:], p[1:]) - energy(q[:-1] + dq, p[:-1] + dp)) / e0
    return np.asarray(change, np.float64) / float(np.finfo(np.float64).eps)


def map_deviation(trajectories, span, weights, h: float, m: float, k: float
                  ) -> tuple[np.ndarray, float]:
    """`(ΔM, Δdet)` in units of float64's eps: the float64 oscillator step seen as a linear map.

    `trajectories` is a sequence of `(q, p)` float64 runs (`(n + 1,)` each) of one step. The
    deviation `ΔM` (`(2, 2)`, rows `q`, `p` of the end, columns of the start) is the least-
    squares fit, in long double, of each step's end minus the exact map of its start
    (`exact_increments`) against the start; what the fit leaves is the rounding that varies
    from step to step. `Δdet = det(M + ΔM) − det(M)`: the exact map `M` is symplectic
    (determinant 1), so a nonzero `Δdet` is a step that scales phase-space area, and with it
    the energy, by `1 + Δdet` on average: the mean of `energy_bias`.
    """
    starts, deviations = [np.zeros((0, 2), _LD)], [np.zeros((0, 2), _LD)]
    for q, p in trajectories:
        q, p = (np.asarray(x, np.float64).astype(_LD) for x in (q, p))
        dq, dp = exact_increments(span, weights, h, q[:-1], p[:-1], m, k)
        starts.append(np.stack([q[:-1], p[:-1]], axis=1))
        deviations.append(np.stack([q[1:] - (q[:-1] + dq), p[1:] - (p[:-1] + dp)], axis=1))
    x, d = np.concatenate(starts), np.concatenate(deviations)
    if x.shape[0] < 2:
        raise ValueError(f"map_deviation needs at least two steps to fit a 2 x 2 map, got "
                         f"{x.shape[0]}")
    # normal equations of the 2 x 2 fit, solved by Cramer's rule (long double throughout)
    g, r = x.T @ x, x.T @ d
    det_g = g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0]
    inverse = np.array([[g[1, 1], -g[0, 1]], [-g[1, 0], g[0, 0]]], _LD) / det_g
    dm = (inverse @ r).T
    unit_q, unit_p = exact_increments(span, weights, h, np.array([1.0, 0.0]),
                                      np.array([0.0, 1.0]), m, k)
    exact = np.eye(2, dtype=_LD) + np.stack([unit_q, unit_p])
    a, b, c, e = exact[0, 0], exact[0, 1], exact[1, 0], exact[1, 1]
    # det(M + ΔM) − det(M), without forming det(M + ΔM) (it would round to 1)
    change = (e * dm[0, 0] - c * dm[0, 1] - b * dm[1, 0] + a * dm[1, 1]
              + dm[0, 0] * dm[1, 1] - dm[0, 1] * dm[1, 0])
    eps = float(np.finfo(np.float64).eps)
    return np.asarray(dm, np.float64) / eps, float(change) / eps


def oscillator_runs(solver, steps: int, phases, h: float = 0.5, m: float = 1.0,
                    k: float = 0.5, amplitude: float = 0.5
                    ) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """Float64 runs of `steps` steps of `h` of `solver` on the oscillator `m`, `k`, one from
    each state of energy `k·amplitude²/2` at the angles `phases` (`q = amplitude·cos φ`,
    `p = −m ω amplitude·sin φ`), compiled once: the trajectories `(q, p)` (`(steps + 1,)`
    each) and the histogram of the root finder's updates per step, summed over the runs.
    A run that fails raises `RuntimeError`; float64 needs `jax_enable_x64` (else
    `ValueError`)."""
    phases = np.atleast_1d(np.asarray(phases, np.float64))
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if phases.ndim != 1 or phases.size == 0:
        raise ValueError(f"phases must be a non-empty sequence of angles, got {phases!r}")
    if not jax.config.jax_enable_x64:
        raise ValueError("oscillator_runs compares float64 runs with the exact map: enable "
                         "float64 first, jax.config.update('jax_enable_x64', True)")
    problem = harmonic_oscillator(m=m, k=k, dtype=jnp.float64)
    omega = (k / m) ** 0.5

    @jax.jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, 0.0, steps * h, h, y0, args=problem.args, max_steps=steps,
            saveat=diffrax.SaveAt(t0=True, steps=True, solver_state=True), throw=False,
        )

    trajectories, histogram = [], 0
    for phase in phases:
        y0 = (jnp.array([amplitude * np.cos(phase)]),
              jnp.array([-m * omega * amplitude * np.sin(phase)]))
        sol = run(y0)
        if sol.result != diffrax.RESULTS.successful:
            raise RuntimeError(f"the run from phase {phase} failed: {sol.result}")
        trajectories.append((np.asarray(sol.ys[0])[:, 0], np.asarray(sol.ys[1])[:, 0]))
        histogram = histogram + np.asarray(sol.solver_state.histogram)
    return trajectories, np.asarray(histogram)


class BiasStatistics(NamedTuple):
    """What rounding adds to the energy per step along some trajectories, in units of eps
    (`bias_statistics`): the `mean` change (the drift rate), its standard error `se`, the
    `rms` change, and `det_change` of `map_deviation` (which accounts for the mean)."""

    mean: float
    se: float
    rms: float
    det_change: float


def bias_statistics(trajectories, span, weights, h: float, m: float, k: float
                    ) -> BiasStatistics:
    """`energy_bias` over all steps of `trajectories` (`(q, p)` runs of one step), with its
    standard error, and `map_deviation`'s determinant change."""
    if len(trajectories) == 0:
        raise ValueError("bias_statistics needs at least one trajectory, got none")
    changes = np.concatenate([energy_bias(q, p, span, weights, h, m, k)
                              for q, p in trajectories])
    _, det_change = map_deviation(trajectories, span, weights, h, m, k)
    return BiasStatistics(float(np.mean(changes)), float(np.std(changes) / np.sqrt(changes.size)),
                          float(np.sqrt(np.mean(changes**2))), det_change)
