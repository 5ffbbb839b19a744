"""The long-run study (issue 28): final error and energy error against wall time over long spans.

Variational solvers on constant steps are compared with classical peers (diffrax `Dopri8` and
`Tsit5` under a PID controller, scipy's `DOP853`, `SemiImplicitEuler` on constant steps) on
spans of many periods. Each timed run saves a few hundred times, so memory does not grow with
the number of steps. The energy error is read at step ends only: the saved times of a
constant-step run fall on its step grid; an adaptive run is repeated untimed, with the same
controller, keeping the energy of every step end (its dense output between steps can be far
less accurate than its steps). One compilation serves every run of a solver on a problem and
span: the end time, the step or the tolerances and the save times are traced, and the
compiling call runs over a short span.

References: the closed forms (harmonic oscillator, Kepler) are evaluated in extended precision,
since in float64 the rounding of the phase grows with the span. The other problems are
integrated in extended precision with the package's order-16 GBS steps
(`problems.stored.gbs_integrate`) on the problem's own equations; the problem's float64
reference beyond its stored span is DOP853 at `rtol = 1e-13`, too coarse for long spans.

Outputs in `out`: `long_run.csv` (one row per run, streamed), `energy_series.csv` (the running
maximum of the energy error over time, sampled), `references.csv`, `report.md` and the figures
`<problem>_error.png`, `<problem>_energy.png` and `energy_growth.png`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import problems as _problems
from ..activations import tanh
from ..ansatz.shallow import ShallowNetBasis
from ..fixed_point import FixedPointIteration
from ..methods import CGVI
from ..problems import Problem
from ..projection import RoundoffNewton
from ..quadrature import GaussLegendre
from ..seeding.trajectories import HermiteExtrapolation
from ..solver import NetworkVI
from ..step_size import RetryFailedSteps
from .harness import (
    Adaptive,
    Entry,
    Fixed,
    NotSeparable,
    SciPy,
    diffrax_metrics,
    energy_errors,
    energy_fn,
    iteration_summary,
    numpy_rhs,
    read_rows,
    relative_error,
    scipy_run,
    timed,
    write_rows,
)
from .status import classify

__all__ = [
    "VARIATIONAL",
    "PEERS",
    "LongRunProblem",
    "PROBLEMS",
    "QUICK_RTOLS",
    "FULL_RTOLS",
    "Reference",
    "reference_end",
    "growth_exponent",
    "TARGETS",
    "run_study",
    "plan_size",
    "cheapest",
    "write_report",
    "code_version",
    "select",
    "cli",
]

# -- what is compared: edit here -----------------------------------------------------------------
# The variational solvers, on constant steps. Factories, so that a changed default of the
# library is picked up and nothing is built at import.
VARIATIONAL: dict[str, Callable[[], diffrax.AbstractSolver]] = {
    "CGVI(7) round-off": lambda: CGVI(7, root_finder=RoundoffNewton(ftol=0.0)),
    "CGVI(7)": lambda: CGVI(7),
    "CGVI(7) chord": lambda: CGVI(7, root_finder=FixedPointIteration(ftol=1.0)),
    "CGVI(7) chord round-off": lambda: CGVI(7, root_finder=FixedPointIteration(ftol=0.0)),
    "CGVI(7) kinetic round-off": lambda: CGVI(
        7, root_finder=FixedPointIteration(ftol=0.0, matrix="kinetic")
    ),
    "CGVI(7) reference form": lambda: CGVI(7, root_finder=RoundoffNewton(ftol=0.0),
                                           initial_trajectory_method=HermiteExtrapolation()),
    "NetworkVI": lambda: NetworkVI(ShallowNetBasis(tanh, 10), GaussLegendre(8)),
    "NetworkVI round-off": lambda: NetworkVI(ShallowNetBasis(tanh, 10), GaussLegendre(8),
                                             root_finder=RoundoffNewton(ftol=0.0)),
}

# The classical peers (`atol = atol_ratio · rtol`; the problem's `atol_ratio` replaces 1.0).
PEERS: tuple[Entry, ...] = (
    Adaptive("Dopri8", diffrax.Dopri8(), atol_ratio=1.0),
    Adaptive("Tsit5", diffrax.Tsit5(), atol_ratio=1.0),
    SciPy("scipy DOP853", "DOP853", atol_ratio=1.0),
    Fixed("SemiImplicitEuler", diffrax.SemiImplicitEuler(), separable=True),
)

QUICK_RTOLS = (1e-10, 1e-12, 1e-13, 1e-14)
FULL_RTOLS = (1e-9, 1e-10, 1e-11, 1e-12, 1e-13, 1e-14)
SCIPY_MIN_RTOL = 2.3e-14  # scipy raises smaller tolerances to 100·eps; such runs are left out
TARGETS = (1e-8, 1e-10)
ADAPTIVE_MAX_STEPS = 2**28  # no buffer grows with it: the timed runs save a few hundred times
ENERGY_MAX_STEPS = 2**25  # the energy of every step end is kept: 16 bytes per step


@dataclasses.dataclass(frozen=True)
class LongRunProblem:
    """One problem of the study.

    - `make`: builds the float64 `Problem` (its span is replaced by the study's).
    - `period`: the time unit of the spans and step counts (a period of the motion).
    - `unit`: how the report names that unit.
    - `quick_spans`, `full_spans`: spans in periods; each run ends `end_phase` periods later,
      so that the end is no turning point (the oscillator and Kepler start at one; back
      there, the error of a symplectic method would be its phase error alone).
    - `steps`: steps per period of the variational solvers (their front; a fraction is
      fine where the span makes the step count whole).
    - `sie_steps`: steps per period of `SemiImplicitEuler` (first order: many more).
    - `atol_ratio`: `atol / rtol` of the adaptive peers (small where some components are tiny).
    - `reference_step`: step of the extended-precision GBS reference; `None` for a closed form.
    """

    make: Callable[[], Problem]
    period: float
    unit: str
    quick_spans: tuple[int, ...]
    full_spans: tuple[int, ...]
    steps: tuple[float, ...]
    sie_steps: tuple[float, ...]
    atol_ratio: float = 1.0
    reference_step: float | None = None
    end_phase: float = 0.125


def _f64(make, **kw) -> Callable[[], Problem]:
    return lambda: make(dtype=jnp.float64, **kw)


TWO_PI = 2 * math.pi
PROBLEMS: dict[str, LongRunProblem] = {
    # m = 1, k = 0.5: ω = 1/√2, period 2π√2.
    "harmonic_oscillator": LongRunProblem(
        _f64(_problems.harmonic_oscillator), TWO_PI * math.sqrt(2), "periods (2π√2)",
        (100,), (1_000, 10_000, 100_000), (1.5, 2, 3, 4), (100, 1000)),
    "kepler_e0.5": LongRunProblem(
        _f64(_problems.kepler, eccentricity=0.5), TWO_PI, "periods (2π)",
        (100,), (1_000, 10_000, 100_000), (16, 24, 32, 48), (1000, 10_000)),
    # Constant steps must resolve the perihelion passage (r = 0.1): hundreds per period.
    "kepler_e0.9": LongRunProblem(
        _f64(_problems.kepler, eccentricity=0.9), TWO_PI, "periods (2π)",
        (100,), (1_000, 10_000, 100_000), (300, 450, 600, 800, 1000), (10_000,)),
    # The default orbit (H₀ = 0.135) is chaotic: no reference holds over long spans (two
    # extended-precision solutions with different steps part). This one (H₀ = 0.0207) is
    # regular.
    "henon_heiles": LongRunProblem(
        _f64(_problems.henon_heiles, q0=(0.1, 0.1), p0=(0.1, 0.1)), TWO_PI,
        "periods (2π, the linear period)", (100,), (1_000, 10_000, 100_000), (3, 4, 6, 8),
        (100, 1000), reference_step=0.25),
    # Units of 1000 days (Jupiter's period is 4333 days); 10⁵ days is a target of the issue.
    # Pluto's momentum is tiny (mass 7.7e-9): the peers' atol must be far below rtol.
    "outer_solar_system": LongRunProblem(
        _f64(_problems.outer_solar_system), 1000.0, "× 1000 days", (100,), (100, 1000, 10_000),
        (1, 2, 3, 5), (100, 1000), atol_ratio=1e-12, reference_step=20.0),
}


# -- references ----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Reference:
    """The reference final position of one span and what is known of its accuracy.

    - `q`: float64 final position.
    - `method`: how it was obtained.
    - `error`: estimated relative error of `q` (self-check), `None` where not estimated.
    - `float64_difference`: relative difference to the problem's own float64 reference.
    - `cost_s`: wall time of computing it.
    """

    q: np.ndarray
    method: str
    error: float | None
    float64_difference: float | None
    cost_s: float


def _ld(x) -> np.ndarray:
    return np.asarray(x, dtype=np.longdouble)


def _harmonic_end(problem: Problem, tau: float) -> np.ndarray:
    m, k = _ld(problem.params["m"]), _ld(problem.params["k"])
    omega = np.sqrt(k / m)
    q0, p0 = (_ld(np.asarray(x, np.float64)) for x in problem.y0)
    theta = omega * _ld(tau)
    return q0 * np.cos(theta) + p0 / (m * omega) * np.sin(theta)


def _kepler_end(problem: Problem, tau: float) -> np.ndarray:
    e = _ld(problem.params["eccentricity"])
    pi = 4 * np.arctan(_ld(1))
    mean = _ld(tau)
    turns = np.floor((mean + pi) / (2 * pi))
    m = mean - 2 * pi * turns
    ecc = m + _ld(0.85) * e * np.sign(np.sin(m))
    tol = 4 * np.finfo(np.longdouble).eps
    for _ in range(100):
        step = (ecc - e * np.sin(ecc) - m) / (1 - e * np.cos(ecc))
        ecc = ecc - step
        if abs(step) <= tol * max(1, abs(ecc)):
            break
    return np.array([np.cos(ecc) - e, np.sqrt(1 - e * e) * np.sin(ecc)])


_EXTENDED_CLOSED_FORMS = {"harmonic_oscillator": _harmonic_end, "kepler": _kepler_end}


def _precision() -> str:
    bits = np.finfo(np.longdouble).nmant + 1
    return f"long double, {bits}-bit mantissa"


def _gbs_end(flow, tau: float, step: float, budget_s: float | None) -> np.ndarray | None:
    """`flow.y0` integrated over `tau` in extended precision with GBS steps of about `step`;
    `None` where the first steps predict more than `budget_s`."""
    from ..problems.stored import gbs_integrate

    n = max(1, math.ceil(tau / step))
    h = _ld(tau) / n
    y = flow.y0.astype(np.longdouble)[None, :]
    probe = min(n, 20)
    start = time.perf_counter()
    y = gbs_integrate(flow.rhs, y, np.full(1, h * probe), probe)
    if budget_s is not None and (time.perf_counter() - start) * n / probe > budget_s:
        return None
    if n > probe:
        y = gbs_integrate(flow.rhs, y, np.full(1, h * (n - probe)), n - probe)
    return y[0]


def reference_end(problem: Problem, t1: float, step: float | None = None,
                  budget_s: float | None = None) -> Reference:
    """The final position at `t1` as accurately as affordable.

    Closed forms are evaluated in extended precision. Otherwise, with `step`, the problem's
    equations are integrated in extended precision with GBS steps of about `step` and again
    with `2·step` (the difference is the error estimate); where that is predicted to take more
    than `budget_s`, the problem's own reference is used, its error estimated against scipy's
    DOP853 at `rtol = 2.3e-14`."""
    start = time.perf_counter()
    tau = t1 - problem.t0
    q64 = problem.reference(np.array([t1]))[0][0]
    d = problem.dim
    closed = _EXTENDED_CLOSED_FORMS.get(problem.name)
    if problem.reference_method == "closed form" and closed is not None:
        q = closed(problem, tau)
        return Reference(np.asarray(q, np.float64), f"closed form ({_precision()})", None,
                         relative_error(q64, np.asarray(q, np.float64)),
                         time.perf_counter() - start)
    flow = problem.reference_flow
    if step is not None and hasattr(flow, "rhs"):
        fine = _gbs_end(flow, tau, step, None if budget_s is None else budget_s / 1.5)
        if fine is not None:
            coarse = _gbs_end(flow, tau, 2 * step, None)
            q = np.asarray(fine[:d], np.float64)
            error = float(np.max(np.abs(fine[:d] - coarse[:d])) / np.max(np.abs(fine[:d])))
            return Reference(q, f"GBS order 16, h ≈ {step:g} ({_precision()})", error,
                             relative_error(q64, q), time.perf_counter() - start)
    from scipy.integrate import solve_ivp

    y0 = np.concatenate([np.asarray(x, np.float64) for x in problem.y0])
    fun, _ = numpy_rhs(problem)  # at the absolute time: a time-dependent field needs it
    tight = solve_ivp(fun, (problem.t0, t1), y0, method="DOP853", rtol=2.3e-14, atol=1e-16)
    error = relative_error(tight.y[:d, -1], q64) if tight.success else None
    return Reference(q64, f"the problem's own ({problem.reference_method})", error, 0.0,
                     time.perf_counter() - start)


# -- measurements --------------------------------------------------------------------------------
def growth_exponent(ts: np.ndarray, envelope: np.ndarray, t0: float = 0.0,
                    decades: float = 2.0) -> float | None:
    """Log-log slope of the running maximum of the energy error over the last `decades`
    decades of time, fitted on points spread evenly in `log t` (Brouwer's law: 0.5).
    `None` where fewer than 8 distinct points fall in that window or none near its start."""
    tau = np.asarray(ts, np.float64) - t0
    env = np.asarray(envelope, np.float64)
    keep = (tau > 0) & np.isfinite(env)
    tau, env = tau[keep], env[keep]
    start = tau[-1] * 10.0**-decades if tau.size else 0.0
    if tau.size < 8 or tau[0] > 1.5 * start:  # the data must cover the whole window
        return None
    grid = np.geomspace(start, tau[-1], 40)
    index = np.unique(np.clip(np.searchsorted(tau, grid, side="left"), 0, tau.size - 1))
    x, y = tau[index], env[index]
    if index.size < 8 or np.any(y <= 0):
        return None
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def _term(problem: Problem, entry: Fixed | Adaptive):
    if isinstance(entry, Fixed) and entry.separable:
        try:
            return problem.term.separable_terms(problem.y0, problem.args, t0=problem.t0)
        except (ValueError, NotImplementedError) as e:
            raise NotSeparable(f"{problem.name}: {e}") from e
    return problem.term


class _Solve:
    """The compiled solves of one (solver, problem, span): end time, step or tolerances and
    save times are traced, so the whole sweep shares them. Adaptive solvers also get
    `energies(max_steps)`: the same solve saving only the energy, at every step end."""

    def __init__(self, problem: Problem, entry: Fixed | Adaptive, max_steps: int):
        term, solver, t0, args = _term(problem, entry), entry.solver, problem.t0, problem.args
        self.fixed = isinstance(entry, Fixed)
        if self.fixed:
            controller = RetryFailedSteps() if entry.retry else diffrax.ConstantStepSize()
        else:
            controller = lambda rtol, atol: diffrax.PIDController(rtol=rtol, atol=atol)

        def run(y0, t1, step, saveat, steps):
            dt, control = (step[0], controller) if self.fixed else (None, controller(*step))
            return diffrax.diffeqsolve(term, solver, t0, t1, dt, y0, args=args, saveat=saveat,
                                       stepsize_controller=control, max_steps=steps,
                                       throw=False)

        self.solve = eqx.filter_jit(lambda y0, t1, *rest: run(
            y0, t1, rest[:-1], diffrax.SaveAt(ts=rest[-1], t1=True, solver_state=True),
            max_steps))
        hamiltonian = lambda t, y, args: problem.energy(t, *y)
        self._energies = {}

        def energies(steps: int):
            if steps not in self._energies:
                saveat = diffrax.SaveAt(subs=diffrax.SubSaveAt(steps=True, fn=hamiltonian))
                self._energies[steps] = eqx.filter_jit(
                    lambda y0, t1, *rest: run(y0, t1, rest[:-1], saveat, steps))
            return self._energies[steps]

        self.energies = energies


def _save_times(t0: float, t1: float, saves: int, steps: int | None) -> np.ndarray:
    """`saves − 1` interior save times (the end is saved apart): on the step grid of a
    constant-step run of `steps` steps (repeated where `steps < saves`), else evenly
    spaced."""
    k = np.arange(1, saves)
    if steps is None:
        return t0 + (t1 - t0) * k / saves
    return t0 + np.round(k * steps / saves) * ((t1 - t0) / steps)


def _timed_runs(fn, full: tuple, short: tuple, repeats: int, budget_s: float):
    """Compile on `short`, then time `full` up to `repeats` times (fewer past `budget_s`)."""
    _, compile_s = timed(fn, *short)
    times: list[float] = []
    out = None
    for _ in range(max(repeats, 1)):
        out, elapsed = timed(fn, *full)
        times.append(elapsed)
        if sum(times) > budget_s:
            break
    return out, statistics.median(times), compile_s, len(times)


def _reached(ts, t1: float) -> bool:
    return math.isclose(float(ts[-1]), t1, rel_tol=1e-12, abs_tol=1e-12)


def _envelope(err: np.ndarray) -> np.ndarray:
    """Running maximum of energy errors (inf from the first non-finite one on)."""
    return np.maximum.accumulate(np.where(np.isfinite(err), err, np.inf))


def _energy_envelope(problem: Problem, energy, ts, q, p) -> np.ndarray:
    """Running maximum of `|H − H₀|/|H₀|` along a trajectory."""
    return _envelope(energy_errors(problem, energy, np.asarray(ts), np.asarray(q),
                                    np.asarray(p)))


def _record_energy(row: dict, problem: Problem, ts, envelope: np.ndarray,
                   series: list[dict]) -> None:
    """Energy error, growth exponent and a sampled energy series of a run into `row`."""
    ts, first = np.unique(np.asarray(ts, np.float64), return_index=True)  # saves may repeat
    envelope = np.asarray(envelope)[first]
    later = ts > problem.t0
    ts, envelope = ts[later], envelope[later]
    row["energy_error"] = float(envelope[-1])
    row["growth_exponent"] = growth_exponent(ts, envelope, problem.t0)
    t0 = problem.t0
    grid = np.geomspace(ts[0] - t0, ts[-1] - t0, 60) + t0
    samples = np.unique(np.clip(np.searchsorted(ts, grid), 0, len(ts) - 1))
    keys = ("problem", "periods", "solver", "family", "parameter", "value")
    series += [dict({k: row[k] for k in keys}, t=float(ts[i]), energy_error=float(envelope[i]))
               for i in samples]


def _scipy_step_ends(problem: Problem, entry: SciPy, rtol: float, grid: np.ndarray):
    """scipy's integrator stepped by hand: the state at the first step end at or after each
    time of `grid` (so the energy is read where the method defines it, not on its dense
    output). Returns `(steps, ts, q, p)` or `None` if it failed."""
    import scipy.integrate

    fun, _ = numpy_rhs(problem)
    y0 = np.concatenate([np.asarray(x, np.float64) for x in problem.y0])
    stepper = getattr(scipy.integrate, entry.method)(
        fun, problem.t0, y0, problem.t1, rtol=rtol, atol=rtol * entry.atol_ratio)
    ts, ys, k, steps = [], [], 0, 0
    while stepper.status == "running" and k < len(grid):
        stepper.step()
        steps += 1
        if stepper.t >= grid[k]:
            ts.append(stepper.t)
            ys.append(stepper.y.copy())
            k = int(np.searchsorted(grid, stepper.t, side="right"))
    if stepper.status == "failed" or not ts:
        return None
    ys = np.array(ys)
    d = problem.dim
    return steps, np.array(ts), ys[:, :d], ys[:, d:]


def _run_one(row: dict[str, Any], problem: Problem, entry: Entry, value: float, *,
             period: float, runner: _Solve | None, saves: int, repeats: int, budget_s: float,
             energy, q_ref: np.ndarray, series: list[dict]) -> None:
    """Measure one run into `row` (which already names the problem, span and solver).

    The timed run gives the status, cost and final error. The energy is read at step ends:
    at the save times of a constant-step run (they lie on its step grid); for the adaptive
    solvers at the first step end at or after each save time, from an untimed repeat of the
    same solve (their dense output between steps can be far less accurate than their steps:
    `energy_error_dense` keeps its value at the save times)."""
    t0, t1 = problem.t0, problem.t1
    d = problem.dim
    if isinstance(entry, SciPy):
        grid = np.append(_save_times(t0, t1, saves, None), t1)
        res, wall, n = scipy_run(problem, entry, t1, value, repeats, budget_s, t_eval=grid)
        row.update(status=classify(res), steps=None, nfev=res.nfev, wall_s=wall,
                   compile_s=0.0, repeats=n)
        if row["status"] != "ok":
            return
        if not _reached(res.t, t1):
            row["status"] = "error:EndNotReached"
            return
        row["error"] = relative_error(res.y[:d, -1], q_ref)
        row["energy_error_dense"] = float(
            _energy_envelope(problem, energy, res.t, res.y[:d].T, res.y[d:].T)[-1])
        ends = _scipy_step_ends(problem, entry, value, grid)
        if ends is not None:
            row["steps"] = ends[0]
            _record_energy(row, problem, ends[1], _energy_envelope(problem, energy, *ends[1:]),
                           series)
        return
    f64 = jnp.float64
    if isinstance(entry, Fixed):
        steps = int(value)
        dt = (t1 - t0) / steps
        ts = _save_times(t0, t1, saves, steps)
        full = (problem.y0, jnp.asarray(t1, f64), jnp.asarray(dt, f64), jnp.asarray(ts, f64))
        short_t1 = t0 + dt
        short = (problem.y0, jnp.asarray(short_t1, f64), jnp.asarray(dt, f64),
                 jnp.full(ts.shape, short_t1, f64))
        row["dt"] = dt
    else:
        ts = _save_times(t0, t1, saves, None)
        tol = (jnp.asarray(value, f64), jnp.asarray(value * entry.atol_ratio, f64))
        full = (problem.y0, jnp.asarray(t1, f64), *tol, jnp.asarray(ts, f64))
        short_t1 = t0 + 0.1 * period
        short = (problem.y0, jnp.asarray(short_t1, f64), *tol, jnp.full(ts.shape, short_t1, f64))
    sol, wall, compile_s, n = _timed_runs(runner.solve, full, short, repeats, budget_s)
    row.update(diffrax_metrics(problem, entry, sol))
    row.update(wall_s=wall, compile_s=compile_s, repeats=n)
    state = sol.solver_state
    if getattr(state, "histogram", None) is not None:
        summary = iteration_summary(state)
        row.update(it_mean=summary["it_mean"], it_max=summary["it_max"])
    if row["status"] != "ok":
        return
    if not _reached(sol.ts, t1):
        row["status"] = "error:EndNotReached"
        return
    row["error"] = relative_error(np.asarray(sol.ys[0])[-1], q_ref)
    if runner.fixed:
        _record_energy(row, problem, sol.ts, _energy_envelope(problem, energy, sol.ts, *sol.ys),
                       series)
        return
    row["energy_error_dense"] = float(_energy_envelope(problem, energy, sol.ts, *sol.ys)[-1])
    # The same solve again (same steps), keeping the energy of every step end; read at the
    # first step end at or after each save time, as for scipy.
    budget = 1 << max(int(row["steps"]) + int(row.get("rejected") or 0) + 16, 64).bit_length()
    if budget > ENERGY_MAX_STEPS:
        row["message"] = f"energy not measured: {row['steps']} steps are too many to keep"
        return
    again = runner.energies(budget)(*full)
    t_steps = np.asarray(again.ts)
    keep = np.isfinite(t_steps)
    t_steps, h = t_steps[keep], np.asarray(again.ys)[keep]
    h0 = float(problem.energy(jnp.asarray(t0, f64), *(jnp.asarray(x, f64) for x in problem.y0)))
    pick = np.unique(np.append(np.searchsorted(t_steps, ts, side="left"), len(t_steps) - 1))
    pick = pick[pick < len(t_steps)]
    err = np.abs(h[pick] - h0) / (abs(h0) if h0 != 0 else 1.0)
    _record_energy(row, problem, t_steps[pick], _envelope(err), series)


# -- the study -----------------------------------------------------------------------------------
COLUMNS = (
    "problem", "periods", "t1", "solver", "family", "parameter", "value", "steps_per_period",
    "dt", "status", "steps", "rejected", "nfev", "wall_s", "compile_s", "repeats", "error",
    "energy_error", "energy_error_dense", "growth_exponent", "it_mean", "it_max", "iterations",
    "max_step_iterations", "ref_error", "message",
)
SERIES_COLUMNS = ("problem", "periods", "solver", "family", "parameter", "value", "t",
                  "energy_error")
REFERENCE_COLUMNS = ("problem", "periods", "unit", "t1", "method", "error",
                     "float64_difference", "cost_s")
CSV_NAME, SERIES_NAME, REFERENCE_NAME = "long_run.csv", "energy_series.csv", "references.csv"


def _peer_sweep(peer: Entry, config: LongRunProblem, rtols: Sequence[float]) -> tuple:
    if isinstance(peer, Fixed):
        return tuple(config.sie_steps if peer.separable else config.steps)
    if isinstance(peer, SciPy):
        return tuple(r for r in rtols if r >= SCIPY_MIN_RTOL)
    return tuple(rtols)


def _entries(config: LongRunProblem, solvers: Mapping[str, Callable], peers: Sequence[Entry],
             rtols: Sequence[float]) -> list[tuple[Entry, tuple]]:
    """(entry, sweep) per solver: steps per period for the constant-step ones, rtols else."""
    out: list[tuple[Entry, tuple]] = [
        (Fixed(name, make(), family="ours"), tuple(config.steps))
        for name, make in solvers.items()
    ]
    for peer in peers:
        if not isinstance(peer, Fixed):
            peer = dataclasses.replace(peer, atol_ratio=config.atol_ratio)
        out.append((peer, _peer_sweep(peer, config, rtols)))
    return out


def plan_size(problems: Mapping[str, LongRunProblem], spans: Mapping[str, Sequence[int]],
              solvers: Mapping[str, Callable], peers: Sequence[Entry],
              rtols: Sequence[float]) -> int:
    """The number of runs (rows) a study will make, for a progress bar."""
    return sum(
        (len(solvers) * len(c.steps) + sum(len(_peer_sweep(p, c, rtols)) for p in peers))
        * len(spans[name])
        for name, c in problems.items()
    )


def run_study(
    out: str,
    *,
    problems: Mapping[str, LongRunProblem] | None = None,
    spans: Mapping[str, Sequence[int]] | None = None,
    full: bool = False,
    solvers: Mapping[str, Callable] | None = None,
    peers: Sequence[Entry] = PEERS,
    rtols: Sequence[float] | None = None,
    saves: int = 400,
    repeats: int = 3,
    budget_s: float = 2.0,
    max_run_s: float | None = None,
    reference_budget_s: float | None = None,
    progress: Any = None,
    command: str = "",
) -> list[dict[str, Any]]:
    """Run the study and write its CSVs, `report.md` and figures into `out`.

    **Arguments:**

    - `problems`: name → `LongRunProblem` (default `PROBLEMS`).
    - `spans`: name → spans in periods (default each problem's quick or full spans).
    - `full`: the full spans and `FULL_RTOLS` instead of the quick ones.
    - `solvers`: the variational solvers, name → factory (default `VARIATIONAL`).
    - `peers`: the classical entries (default `PEERS`).
    - `rtols`: tolerances of the adaptive peers (default `QUICK_RTOLS` / `FULL_RTOLS`).
    - `saves`: saved times per run (each run's maximum energy error is taken over them).
    - `repeats`, `budget_s`: timed runs after compilation; no new repeat once `budget_s` is
      spent.
    - `max_run_s`: a run predicted (from the same solver's previous span, or a smaller step
      count) to take longer is skipped and recorded with status `skipped`.
    - `reference_budget_s`: the extended-precision reference is replaced by the problem's own
      reference where predicted to take longer.
    - `progress`: a `tqdm`-like object, or `None`.
    - `command`, in the report: the command that ran the study.
    """
    problems = dict(PROBLEMS if problems is None else problems)
    solvers = dict(VARIATIONAL if solvers is None else solvers)
    rtols = tuple(rtols if rtols is not None else (FULL_RTOLS if full else QUICK_RTOLS))
    if spans is None:
        spans = {n: (c.full_spans if full else c.quick_spans) for n, c in problems.items()}
    os.makedirs(out, exist_ok=True)
    paths = {k: os.path.join(out, k) for k in (CSV_NAME, SERIES_NAME, REFERENCE_NAME)}
    for path in paths.values():
        if os.path.exists(path):
            os.remove(path)
    settings = dict(saves=saves, repeats=repeats, budget_s=budget_s, max_run_s=max_run_s,
                    progress=progress, paths=paths)
    code = code_version()
    start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    for name, config in problems.items():
        base = config.make()
        entries = _entries(config, solvers, peers, rtols)
        walls: dict[tuple[str, float], tuple[int, float]] = {}  # (solver, value) -> span, wall
        for periods in sorted(spans[name]):
            problem = base.with_span(base.t0 + (periods + config.end_phase) * config.period)
            if progress is not None:
                progress.set_postfix_str(f"{name} {periods}: reference")
            ref = reference_end(problem, problem.t1, config.reference_step, reference_budget_s)
            write_rows([dict(problem=name, periods=periods, unit=config.unit, t1=problem.t1,
                             method=ref.method, error=ref.error,
                             float64_difference=ref.float64_difference, cost_s=ref.cost_s)],
                       paths[REFERENCE_NAME], append=True, columns=REFERENCE_COLUMNS)
            energy = energy_fn(problem)
            for entry, sweep in entries:
                rows += _sweep(name, config, periods, problem, entry, sweep, ref, energy, walls,
                               **settings)
            jax.clear_caches()  # one span's executables are not needed again
    write_report(out, command=command, elapsed=time.perf_counter() - start, code=code)
    return rows


def code_version() -> str:
    """The git commit of the package and its uncommitted files under `diffrax_vi/` (read
    without taking git's locks), or `""` outside a git checkout."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    git = ["git", "--no-optional-locks", "-C", root]
    try:
        head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=30).stdout.strip()
        changed = subprocess.run([*git, "status", "--porcelain", "--", "diffrax_vi"],
                                 capture_output=True, text=True, timeout=30).stdout.split("\n")
    except (OSError, subprocess.SubprocessError):
        return ""
    if not head:
        return ""
    files = [line[3:] for line in changed if line.strip()]
    return f"git {head}" + (f", uncommitted: {', '.join(files)}" if files else "")


def _sweep(name: str, config: LongRunProblem, periods: int, problem: Problem, entry: Entry,
           sweep: tuple, ref: Reference, energy, walls: dict, *, saves: int, repeats: int,
           budget_s: float, max_run_s: float | None, progress: Any,
           paths: Mapping[str, str]) -> list[dict[str, Any]]:
    """One solver's sweep on one span: a row per setting, streamed to the CSVs."""
    fixed = isinstance(entry, Fixed)
    length = periods + config.end_phase
    values = [max(1, round(s * length)) for s in sweep] if fixed else list(sweep)
    runner, stop = None, None
    rows: list[dict[str, Any]] = []
    series: list[dict] = []
    for value, label in zip(values, sweep, strict=True):
        if progress is not None:
            progress.set_postfix_str(f"{name} {periods}: {entry.name} {label:g}")
        row: dict[str, Any] = dict(
            problem=name, periods=periods, t1=problem.t1, solver=entry.name,
            family=entry.family, parameter=entry.parameter, value=value, ref_error=ref.error)
        if fixed:
            row["steps_per_period"] = label
        guess = _predicted_wall(walls, entry, label, periods)
        if stop is not None:  # e.g. not separable: every setting fails the same way
            row.update(status=stop[0], message=stop[1])
        elif max_run_s is not None and guess is not None and guess > max_run_s:
            row.update(status="skipped",
                       message=f"predicted {guess:.0f} s > {max_run_s:.0f} s per run")
        else:
            try:
                if runner is None and not isinstance(entry, SciPy):
                    budget = entry.step_budget(max(values)) if fixed else ADAPTIVE_MAX_STEPS
                    runner = _Solve(problem, entry, budget)
                _run_one(row, problem, entry, value, period=config.period, runner=runner,
                         saves=saves, repeats=repeats, budget_s=budget_s, energy=energy,
                         q_ref=ref.q, series=series)
            except Exception as e:  # one failing run never stops the study
                row["status"] = classify(e)
                row["message"] = str(e).splitlines()[0][:200] if str(e) else ""
            if row["status"].startswith("error:Not"):
                stop = (row["status"], row.get("message", ""))
        if row.get("wall_s") is not None:
            walls[(entry.name, label)] = (periods, row["wall_s"])
        rows.append(row)
        write_rows([row], paths[CSV_NAME], append=True, columns=COLUMNS)
        if progress is not None:
            progress.update(1)
    if series:
        write_rows(series, paths[SERIES_NAME], append=True, columns=SERIES_COLUMNS)
    return rows


def _predicted_wall(walls: Mapping, entry: Entry, label: float, periods: int) -> float | None:
    """The wall time of a run predicted from the same solver and setting on the previous span
    (linear in the span), or from a cheaper setting on this span (linear in the steps)."""
    known = walls.get((entry.name, label))
    if known is not None and known[0] != periods:
        return known[1] * periods / known[0]
    if isinstance(entry, Fixed):
        cheaper = [(lab, w) for (n, lab), (p, w) in walls.items()
                   if n == entry.name and p == periods and lab < label]
        if cheaper:
            lab, w = max(cheaper)
            return w * label / lab
    return None


# -- report --------------------------------------------------------------------------------------
def _fmt(x: Any, spec: str = ".1e") -> str:
    if x is None or x == "" or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return format(x, spec) if isinstance(x, int | float) else str(x)


def _setting(r: dict) -> str:
    if r["parameter"] == "steps":
        return f"{_fmt(r.get('steps_per_period'), 'g')}/period"
    return f"rtol {r['value']:.0e}"


def _ok(rows: Sequence[dict]) -> list[dict]:
    return [r for r in rows if r.get("status") == "ok" and r.get("error") is not None
            and r.get("wall_s")]


def cheapest(rows: Sequence[dict], target: float) -> dict | None:
    """The cheapest `ok` run whose final error is at most `target` (`None` if there is none)."""
    good = [r for r in _ok(rows) if r["error"] <= target]
    return min(good, key=lambda r: r["wall_s"]) if good else None


def _span_table(rows: Sequence[dict], targets: Sequence[float]) -> str:
    from .report import markdown

    header = ["solver", "ok / runs", "best final error", "min max-energy error"]
    for t in targets:
        header += [f"cheapest ≤ {t:.0e}: wall s", "setting", "energy error"]
    header.append("iterations / step")
    body = []
    for solver in dict.fromkeys(r["solver"] for r in rows):
        rs = [r for r in rows if r["solver"] == solver]
        ok = _ok(rs)
        cells = [solver, f"{len(ok)} / {len(rs)}",
                 _fmt(min((r["error"] for r in ok), default=None)),
                 _fmt(min((r["energy_error"] for r in ok), default=None))]
        for t in targets:
            c = cheapest(rs, t)
            cells += (["–", "–", "–"] if c is None else
                      [_fmt(c["wall_s"], ".3g"), _setting(c), _fmt(c["energy_error"])])
        its = [r["it_mean"] for r in ok if r.get("it_mean") is not None]
        cells.append(", ".join(f"{x:.1f}" for x in its) if its else "–")
        body.append(cells)
    return markdown(header, body)


def _winners(rows: Sequence[dict], targets: Sequence[float],
             units: Mapping[str, str]) -> list[list[str]]:
    out = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        for periods in dict.fromkeys(r["periods"] for r in rows if r["problem"] == problem):
            rs = [r for r in rows if r["problem"] == problem and r["periods"] == periods]
            for t in targets:
                c = cheapest(rs, t)
                peers = [r for r in rs if r["family"] != "ours"]
                ours = [r for r in rs if r["family"] == "ours"]
                best_peer, best_ours = cheapest(peers, t), cheapest(ours, t)
                ratio = (best_ours["wall_s"] / best_peer["wall_s"]
                         if best_peer and best_ours else None)
                out.append([
                    problem, _span_name(units, problem, periods), f"{t:.0e}",
                    "none reached it" if c is None else
                    f"{c['solver']} ({_setting(c)}, {c['wall_s']:.3g} s)",
                    "–" if best_ours is None else
                    f"{best_ours['solver']} {best_ours['wall_s']:.3g} s",
                    "–" if best_peer is None else
                    f"{best_peer['solver']} {best_peer['wall_s']:.3g} s",
                    _fmt(ratio, ".2g")])
    return out


def _exponents(rows: Sequence[dict], units: Mapping[str, str]) -> list[list[str]]:
    out = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        rs = [r for r in rows if r["problem"] == problem and r["family"] == "ours"]
        ok = [r for r in _ok(rs) if r.get("growth_exponent") is not None]
        if not ok:
            continue
        longest = max(r["periods"] for r in ok)
        for solver in dict.fromkeys(r["solver"] for r in ok):
            sel = [r for r in ok if r["solver"] == solver and r["periods"] == longest]
            if sel:
                out.append([problem, _span_name(units, problem, longest), solver, ", ".join(
                    f"{_setting(r).split('/')[0]}: {r['growth_exponent']:.2f} "
                    f"({r['energy_error']:.1e})" for r in sel)])
    return out


def _span_name(units: Mapping[str, str], problem: str, periods: Any) -> str:
    return f"{periods} {units.get(problem, 'periods')}"


def _plot(rows: Sequence[dict], problem: str, key: str, label: str, path: str,
          units: Mapping[str, str]) -> None:
    from .report import pyplot

    plt = pyplot()
    rs = [r for r in rows if r["problem"] == problem]
    spans = list(dict.fromkeys(r["periods"] for r in rs))
    fig, axes = plt.subplots(1, len(spans), figsize=(5.5 * len(spans), 4.2), squeeze=False)
    for ax, periods in zip(axes.flat, spans, strict=True):
        for solver in dict.fromkeys(r["solver"] for r in rs):
            pts = sorted((r["wall_s"], r[key]) for r in _ok(rs)
                         if r["solver"] == solver and r["periods"] == periods
                         and r.get(key) and r[key] > 0)
            if not pts:
                continue
            ours = next(r["family"] for r in rs if r["solver"] == solver) == "ours"
            ax.loglog(*zip(*pts, strict=True), "o-" if ours else "s--", label=solver,
                      lw=2 if ours else 1, ms=5 if ours else 4)
        ax.set_title(f"{problem}, {_span_name(units, problem, periods)}", fontsize=10)
        ax.set_xlabel("wall time after compilation [s]")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_growth(series: Sequence[dict], rows: Sequence[dict], path: str,
                 units: Mapping[str, str]) -> None:
    """Running maximum of the energy error against time on the longest span: each solver's
    run at its smallest step or tolerance."""
    from .report import pyplot, subplot_grid

    plt = pyplot()
    problems = list(dict.fromkeys(r["problem"] for r in series))
    if not problems:
        return
    nr, nc = subplot_grid(len(problems))
    fig, axes = plt.subplots(nr, nc, figsize=(5.5 * nc, 4.2 * nr), squeeze=False)
    for ax, problem in zip(axes.flat, problems, strict=False):
        ok = [r for r in _ok(rows) if r["problem"] == problem]
        longest = max(r["periods"] for r in ok)
        for solver in dict.fromkeys(r["solver"] for r in ok):
            runs = [r for r in ok if r["solver"] == solver and r["periods"] == longest]
            if not runs:
                continue
            best = min(runs, key=lambda r: r["value"] if r["parameter"] == "rtol"
                       else -r["value"])
            pts = [(s["t"], s["energy_error"]) for s in series
                   if s["problem"] == problem and s["periods"] == longest
                   and s["solver"] == solver and s["value"] == best["value"]
                   and s["energy_error"] > 0]
            if pts:
                ours = best["family"] == "ours"
                ax.loglog(*zip(*pts, strict=True), "-" if ours else "--", lw=2 if ours else 1,
                          label=f"{solver} ({_setting(best)})")
        ax.set_title(f"{problem}, {_span_name(units, problem, longest)}", fontsize=10)
        ax.set_xlabel("t")
        ax.set_ylabel("max |H − H₀| / |H₀| so far")
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
    from .report import save_grid

    save_grid(plt, fig, axes, len(problems), path)


def write_report(out: str, *, command: str = "", elapsed: float | None = None,
                 code: str = "", targets: Sequence[float] = TARGETS) -> str:
    """`report.md` and the figures from the CSVs in `out` (`code`: the code version run)."""
    from .report import markdown

    path = os.path.join(out, CSV_NAME)
    rows = read_rows(path) if os.path.exists(path) else []
    spath = os.path.join(out, SERIES_NAME)
    series = read_rows(spath) if os.path.exists(spath) else []
    rpath = os.path.join(out, REFERENCE_NAME)
    refs = read_rows(rpath) if os.path.exists(rpath) else []
    units = {r["problem"]: r["unit"] for r in refs if r.get("unit")}
    parts = ["# Long-run study", ""]
    if command:
        parts += [f"Command: `{command}`", ""]
    if elapsed is not None:
        parts += [f"Wall time of the study: {elapsed:.0f} s ({elapsed / 60:.1f} min).", ""]
    if code:
        parts += [f"Code: {code}.", ""]
    parts += [
        f"Machine: {platform.platform()}, python {platform.python_version()}, jax "
        f"{jax.__version__} ({jax.default_backend()}), CPUs available to the process: "
        f"{len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count()}.",
        "",
        "Final error: `max|q(T) − q_ref(T)| / max|q_ref(T)|`, where `T` (see References) lies "
        "a fraction of a period (`LongRunProblem.end_phase`, 1/8 by default) past the span's "
        "whole periods: the oscillator and Kepler start at a turning point, where the error "
        "of a symplectic method would be its phase error alone. Energy error: the largest "
        "`|H − H₀|/|H₀|` over a few hundred step ends spread over the span (for the adaptive "
        "solvers, from an untimed repeat of the same solve; `energy_error_dense` in the CSV is "
        "their value on the dense output). Wall time: median of the timed runs after "
        "compilation. Only runs with status `ok` count.",
        "",
    ]
    if refs:
        parts += ["## References", "", markdown(
            ["problem", "span", "T", "method", "estimated error", "float64 reference differs by",
             "cost s"],
            [[r["problem"], _span_name(units, r["problem"], r["periods"]), _fmt(r["t1"], ".6g"),
              r["method"],
              _fmt(r["error"]), _fmt(r["float64_difference"]), _fmt(r["cost_s"], ".1f")]
             for r in refs]), ""]
    if rows:
        parts += ["## Cheapest run per final error", "",
                  "`ours / peer`: wall time of the cheapest variational run over that of the "
                  "cheapest classical run at the same error level (< 1: the variational solver is "
                  "faster).", "",
                  markdown(["problem", "span", "final error ≤", "cheapest run",
                            "cheapest variational", "cheapest peer", "ours / peer"],
                           _winners(rows, targets, units)), ""]
        exps = _exponents(rows, units)
        if exps:
            parts += ["## Growth of the energy error", "",
                      "Log-log slope of the running maximum of the energy error over the last two "
                      "decades of the longest span measured, per run (steps per period: slope "
                      "(final energy error)). Brouwer's law for round-off is 0.5; a bounded error "
                      "gives 0.", "",
                      markdown(["problem", "span", "solver", "exponents"], exps), ""]
        for problem in dict.fromkeys(r["problem"] for r in rows):
            rs = [r for r in rows if r["problem"] == problem]
            _plot(rs, problem, "error", "final error (relative, q)",
                  os.path.join(out, f"{problem}_error.png"), units)
            _plot(rs, problem, "energy_error", "max |H − H₀| / |H₀|",
                  os.path.join(out, f"{problem}_energy.png"), units)
            parts += [f"## {problem}", "",
                      f"![final error]({problem}_error.png) "
                      f"![energy error]({problem}_energy.png)", ""]
            for periods in dict.fromkeys(r["periods"] for r in rs):
                sel = [r for r in rs if r["periods"] == periods]
                parts += [f"### {_span_name(units, problem, periods)} (T = {sel[0]['t1']:.6g})",
                          "",
                          _span_table(sel, targets), ""]
        if series:
            _plot_growth(series, rows, os.path.join(out, "energy_growth.png"), units)
            parts += ["## Energy error over time", "", "![energy growth](energy_growth.png)", ""]
        bad = [r for r in rows if r.get("status") != "ok"]
        parts += ["## Runs that did not count", ""]
        parts += [markdown(["problem", "span", "solver", "setting", "status", "message"],
                           [[r["problem"], _span_name(units, r["problem"], r["periods"]),
                             r["solver"], _setting(r),
                             r["status"], _fmt(r.get("message"))] for r in bad])
                  if bad else "None: every run ended `ok`.", ""]
    text = "\n".join(parts)
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(text)
    return text


# -- command line --------------------------------------------------------------------------------
DEFAULT_OUT = "benchmarks/results/long_run"


def select(args) -> dict[str, Any]:
    """The keyword arguments of `run_study` from the parsed command line (`--problems` picks
    problems by name, `--solvers` variational solvers by substring; the peers always run)."""
    names = args.problems or list(PROBLEMS)
    unknown = [n for n in names if n not in PROBLEMS]
    if unknown:
        raise SystemExit(f"unknown problem(s) {unknown}; choose from {sorted(PROBLEMS)}")
    solvers = {k: v for k, v in VARIATIONAL.items()
               if not args.solvers or any(s in k for s in args.solvers)}
    if not solvers:
        raise SystemExit(f"no variational solver matches {args.solvers}; "
                         f"choose from {list(VARIATIONAL)}")
    full = bool(args.full)
    spans = getattr(args, "spans", None)
    if spans is not None and (not spans or min(spans) < 1):
        raise SystemExit(f"--spans must be whole numbers of periods >= 1, got {spans}")
    return dict(
        problems={n: PROBLEMS[n] for n in names}, full=full, solvers=solvers,
        spans=None if spans is None else {n: tuple(spans) for n in names},
        repeats=args.repeats or (5 if full else 3), budget_s=10.0 if full else 2.0,
        max_run_s=900.0 if full else 60.0, reference_budget_s=1800.0 if full else 60.0,
    )


def cli(args, command: str = "") -> list[dict[str, Any]]:
    """Run the study from the parsed command line of `python -m diffrax_vi.bench long-run`."""
    import sys

    kwargs = select(args)
    spans = kwargs["spans"] or {n: (c.full_spans if kwargs["full"] else c.quick_spans)
                                for n, c in kwargs["problems"].items()}
    rtols = FULL_RTOLS if kwargs["full"] else QUICK_RTOLS
    bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=plan_size(kwargs["problems"], spans, kwargs["solvers"], PEERS, rtols),
                   desc="long-run", file=sys.stderr, dynamic_ncols=True)
    rows = run_study(args.out, progress=bar, command=command, **kwargs)
    if bar is not None:
        bar.close()
    return rows
