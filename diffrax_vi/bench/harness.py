"""Work-precision and long-time energy measurements of mechanical solvers on a `Problem`.

Each solver comes as an entry (`diffrax_vi.bench.entries`: `Fixed`, `Adaptive`, `SciPy`,
`Heyoka`) that says how to run it and what its sweep parameter is. All runs of one entry on
one problem share one compilation: the end time, the step size and the tolerances are traced
arguments of a single `eqx.filter_jit`-ed `diffeqsolve`. Every run is isolated: an exception
becomes a row with status `error:<ExceptionName>`. Rows go to CSV by
`diffrax_vi.bench.rows`.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._step_size import RetryFailedSteps
from ..problems import Problem
from .entries import Adaptive, Entry, Fixed, Heyoka, NotSeparable, SciPy
from .rows import write_rows
from .status import classify

__all__ = [
    "energy_errors",
    "growth_exponent",
    "iteration_summary",
    "long_time_energy",
    "numpy_rhs",
    "relative_error",
    "timed",
    "work_precision",
]


# -- measurements -----------------------------------------------------------------------------
def relative_error(q: np.ndarray, q_ref: np.ndarray) -> float:
    """`max|q − q_ref| / max|q_ref|` (absolute when `q_ref = 0`): the reference's `ref_err`."""
    q = np.asarray(q, np.float64)
    q_ref = np.asarray(q_ref, np.float64)
    scale = float(np.max(np.abs(q_ref)))
    err = float(np.max(np.abs(q - q_ref)))
    return err / scale if scale > 0 else err


def energy_fn(problem: Problem) -> Callable:
    def energy(ts, qs, ps):
        return jax.vmap(lambda t, q, p: problem.energy(t, q, p))(ts, qs, ps)

    return jax.jit(energy)


def energy_errors(problem: Problem, energy, ts, qs, ps) -> np.ndarray:
    """`|H(t) − H(t0)| / |H(t0)|` along a trajectory, evaluated in float64."""
    h = np.asarray(energy(jnp.asarray(ts, jnp.float64), jnp.asarray(qs, jnp.float64),
                          jnp.asarray(ps, jnp.float64)))
    q0, p0 = (jnp.asarray(x, jnp.float64) for x in problem.y0)
    h0 = float(problem.energy(jnp.asarray(problem.t0, jnp.float64), q0, p0))
    return np.abs(h - h0) / (abs(h0) if h0 != 0 else 1.0)


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


def timed(fn, *args):
    """`fn(*args)` and its wall time in seconds, waiting for the result's arrays."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def iteration_summary(state) -> dict:
    """Steps and nonlinear iterations per step of a solve, from a `NetworkVIState`'s
    counters: `steps`, `it_median` (from the iteration histogram; the lower median),
    `it_mean`, `it_max` (`None` where no step was taken)."""
    steps = int(state.steps)
    if steps == 0:
        return dict(steps=0, it_median=None, it_mean=None, it_max=None)
    cumulative = np.cumsum(np.asarray(state.histogram))
    return dict(
        steps=steps,
        it_median=int(np.searchsorted(cumulative, steps / 2)),
        it_mean=int(state.iterations) / steps,
        it_max=int(state.max_iterations),
    )


def _repeat(fn, args, repeats: int, budget_s: float):
    """Run once to compile, then up to `repeats` more times (stopping when over budget)."""
    out, first = timed(fn, *args)
    times = []
    for _ in range(repeats):
        out, elapsed = timed(fn, *args)
        times.append(elapsed)
        if sum(times) > budget_s:
            break
    wall = statistics.median(times) if times else first
    return out, wall, max(first - wall, 0.0), len(times)


class _DiffraxRunner:
    """One compiled `diffeqsolve` per (entry, problem, max_steps), reused across the sweep."""

    def __init__(self, problem: Problem, entry: Fixed | Adaptive, max_steps: int, saveat):
        self.problem = problem
        self.entry = entry
        self.max_steps = max_steps
        term = problem.term
        if isinstance(entry, Fixed) and entry.separable:
            try:
                term = term.separable_terms(problem.y0, problem.args, t0=problem.t0)
            except (ValueError, NotImplementedError) as e:
                raise NotSeparable(f"{problem.name}: {e}") from e
        solver = entry.solver
        t0 = problem.t0
        args = problem.args

        if isinstance(entry, Fixed):
            controller = RetryFailedSteps() if entry.retry else diffrax.ConstantStepSize()

            @eqx.filter_jit
            def solve(y0, t1, dt):
                return diffrax.diffeqsolve(
                    term, solver, t0, t1, dt, y0, args=args, saveat=saveat,
                    stepsize_controller=controller, max_steps=max_steps,
                    throw=False,
                )

        else:

            @eqx.filter_jit
            def solve(y0, t1, rtol, atol):
                controller = diffrax.PIDController(rtol=rtol, atol=atol)
                return diffrax.diffeqsolve(
                    term, solver, t0, t1, None, y0, args=args, saveat=saveat,
                    stepsize_controller=controller, max_steps=max_steps, throw=False,
                )

        self.solve = solve

    def arguments(self, t1: float, value: float):
        f64 = jnp.float64
        if isinstance(self.entry, Fixed):
            return (self.problem.y0, jnp.asarray(t1, f64),
                    jnp.asarray((t1 - self.problem.t0) / value, f64))
        return (self.problem.y0, jnp.asarray(t1, f64), jnp.asarray(value, f64),
                jnp.asarray(value * self.entry.atol_ratio, f64))


def _iteration_cap(solver) -> int | None:
    return getattr(solver, "root_find_max_steps", None)


def diffrax_metrics(problem, entry, sol) -> dict[str, Any]:
    status = classify(sol, iteration_cap=_iteration_cap(getattr(entry, "solver", None)))
    stats = sol.stats
    row: dict[str, Any] = dict(
        status=status,
        steps=int(stats["num_accepted_steps"]),
        rejected=int(stats.get("num_rejected_steps", 0)),
    )
    state = sol.solver_state
    iterations = getattr(state, "iterations", None)
    if iterations is not None:
        row["iterations"] = int(iterations)
        row["max_step_iterations"] = int(state.max_iterations)
    return row


def _trajectory(sol) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ts = np.asarray(sol.ts)
    keep = np.isfinite(ts)
    q, p = (np.asarray(x)[keep] for x in sol.ys)
    return ts[keep], q, p


def _closed_form_rhs(problem: Problem) -> Callable | None:
    """NumPy Hamilton equations of the problems whose reference needs none."""
    if problem.name == "harmonic_oscillator":
        m, k = problem.params["m"], problem.params["k"]
        return lambda y: np.concatenate([y[1:] / m, -k * y[:1]])
    if problem.name == "kepler":

        def kepler(y):
            q, p = y[:2], y[2:]
            return np.concatenate([p, -q / np.sqrt(q @ q) ** 3])

        return kepler
    return None


def numpy_rhs(problem: Problem) -> tuple[Callable, str]:
    """Hamilton's equations `fun(t, y)` on the flat state `concat(q, p)` (scipy's convention)
    and where they come from: the stored flow's NumPy field (which knows the time of a
    time-dependent problem), a closed form, or the term itself under `jax.jit`."""
    field = getattr(problem.reference_flow, "vector_field", None)
    if field is not None:
        return field, "numpy"
    rhs = getattr(problem.reference_flow, "rhs", None) or _closed_form_rhs(problem)
    if rhs is not None:
        return (lambda t, y: rhs(y)), "numpy"
    term, args = problem.term, problem.args
    d = problem.dim

    @jax.jit
    def vf(t, y):
        v, f = term.vf(t, (y[:d], y[d:]), args)
        return jnp.concatenate([v, f])

    return (lambda t, y: np.asarray(vf(t, jnp.asarray(y)))), "jax"


def scipy_run(problem: Problem, entry: SciPy, t1: float, rtol: float, repeats: int,
               budget_s: float, t_eval=None):
    from scipy.integrate import solve_ivp

    fun, _ = numpy_rhs(problem)
    y0 = np.concatenate([np.asarray(x, np.float64) for x in problem.y0])
    kwargs = dict(method=entry.method, rtol=rtol, atol=rtol * entry.atol_ratio, t_eval=t_eval)
    fun(problem.t0, y0)  # compile the JAX fallback outside the timing
    times = []
    res = None
    for _ in range(max(repeats, 1)):
        start = time.perf_counter()
        res = solve_ivp(fun, (problem.t0, t1), y0, **kwargs)
        times.append(time.perf_counter() - start)
        if sum(times) > budget_s:
            break
    return res, statistics.median(times), len(times)


# -- work-precision ---------------------------------------------------------------------------
def _values_for(entry: Entry, values: Sequence[float] | Mapping[str, Sequence[float]] | None):
    if isinstance(values, Mapping):
        return values.get(entry.name)
    return values


def _check_run(entry: Any, value: Any) -> None:
    """Refuse a solver entry that is not `Fixed`/`Adaptive`/`SciPy`, or a sweep value that is
    not a positive number (step count for `Fixed`, rtol otherwise), naming the culprit."""
    if not isinstance(entry, Fixed | Adaptive | SciPy | Heyoka):
        raise TypeError(
            "solver entries must be Fixed, Adaptive or SciPy (or Heyoka), got "
            f"{type(entry).__name__}"
        )
    kind = "step count" if isinstance(entry, Fixed) else "rtol"
    if not (isinstance(value, int | float | np.integer | np.floating) and value > 0
            and np.isfinite(value)):
        raise ValueError(f"{entry.name}: the {kind} must be a positive number, got {value!r}")
    if isinstance(entry, Fixed) and int(value) != value:
        raise ValueError(f"{entry.name}: the step count must be an integer, got {value!r}")


def work_precision(
    problem: Problem,
    solvers: Sequence[Entry],
    *,
    steps: Sequence[int] | Mapping[str, Sequence[int]] | None = None,
    rtols: Sequence[float] | Mapping[str, Sequence[float]] | None = None,
    repeats: int = 3,
    budget_s: float = 20.0,
    adaptive_max_steps: int = 100_000,
    csv_path: str | None = None,
    progress: Any = None,
    on_rows: Callable[[list[dict[str, Any]]], None] | None = None,
) -> list[dict[str, Any]]:
    """Final error, energy error and cost of each solver over a sweep, on `problem`'s span.

    For each solver and each sweep value, one row with: `problem`, `solver`, `family`,
    `parameter` (`"steps"` or `"rtol"`) and `value`, `status` (see `classify`), `steps`
    taken, `rejected`, `t_end` reached, `error` (`relative_error` of the final `q` against
    `problem.reference`), `energy_error` (max over the step ends of `|H − H₀|/|H₀|`, in
    float64), `wall_s` (median over `repeats` runs after compilation, fewer when the runs
    exceed `budget_s`), `compile_s` (first call minus `wall_s`), `repeats`, and for
    `NetworkVI` the nonlinear `iterations` (total) and `max_step_iterations`.

    **Arguments:**

    - `problem`: the `Problem`; its `t0`, `t1` and `y0` (dtype included) set the run.
    - `solvers`: `Fixed`, `Adaptive`, `SciPy` and `Heyoka` entries.
    - `steps`: step counts over the span for the `Fixed` entries (one list, or a mapping from
      entry name to its own list).
    - `rtols`: relative tolerances for `Adaptive` and `SciPy` entries, heyoka's `tol` for
      `Heyoka` entries (same forms).
    - `repeats`, `budget_s`: timing repeats after the compiling call, and the time after which
      an entry stops repeating a point.
    - `adaptive_max_steps`: step budget of the adaptive runs.
    - `csv_path`: if given, rows are appended to this CSV as they are measured.
    - `progress`: a `tqdm`-like object with `update(n)` and `set_postfix_str(s)`, or `None`.
    - `on_rows`: called with `[row]` as each row is measured (how the sweep executor streams
      them), or `None`.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    for entry in solvers:
        for value in _values_for(entry, steps if isinstance(entry, Fixed) else rtols) or ():
            _check_run(entry, value)
    energy = energy_fn(problem)
    t1 = problem.t1
    q_ref = problem.reference(np.array([t1]))[0][0]
    saveat = diffrax.SaveAt(t0=True, steps=True, solver_state=True)
    rows: list[dict[str, Any]] = []
    for entry in solvers:
        sweep = _values_for(entry, steps if isinstance(entry, Fixed) else rtols) or ()
        point = _WorkPrecisionPoint(problem, entry, sweep, energy, q_ref, saveat, repeats,
                                    budget_s, adaptive_max_steps)
        for value in sweep:
            if progress is not None:
                progress.set_postfix_str(f"{problem.name}: {entry.name} {value:g}")
            row = point.measure(value)
            rows.append(row)
            if csv_path is not None:
                write_rows([row], csv_path, append=True)
            if on_rows is not None:
                on_rows([row])
            if progress is not None:
                progress.update(1)
            if isinstance(row.get("status"), str) and row["status"].startswith("error:Not"):
                break  # e.g. not separable: every value would fail the same way
    return rows


class _WorkPrecisionPoint:
    """The rows of `work_precision` for one entry on one problem, a sweep value at a time;
    the entry's diffrax runs share one compiled solve, built on the first of them."""

    def __init__(self, problem: Problem, entry: Entry, sweep, energy, q_ref, saveat,
                 repeats: int, budget_s: float, adaptive_max_steps: int):
        self.problem, self.entry, self.sweep = problem, entry, sweep
        self.energy, self.q_ref, self.saveat = energy, q_ref, saveat
        self.repeats, self.budget_s = repeats, budget_s
        self.adaptive_max_steps = adaptive_max_steps
        self.runner: _DiffraxRunner | None = None

    def measure(self, value) -> dict[str, Any]:
        """The row of the sweep value `value` (a failing run is a row too)."""
        problem, entry, t1 = self.problem, self.entry, self.problem.t1
        row: dict[str, Any] = dict(
            problem=problem.name, solver=entry.name, family=entry.family,
            parameter=entry.parameter, value=value,
        )
        try:
            ts, q, p = self._run(value, row)
            row["t_end"] = float(ts[-1])
            reached = math.isclose(float(ts[-1]), t1, rel_tol=1e-9, abs_tol=1e-12)
            if row["status"] == "ok" and reached:
                row["error"] = relative_error(q[-1], self.q_ref)
                row["energy_error"] = float(np.max(energy_errors(problem, self.energy, ts, q,
                                                                  p)))
            elif row["status"] == "ok":
                row["status"] = "error:EndNotReached"
        except Exception as e:  # one failing run never stops the sweep
            row["status"] = classify(e)
            row["message"] = str(e).splitlines()[0][:200] if str(e) else ""
        return row

    def _run(self, value, row: dict[str, Any]):
        """Run the entry at `value`, add its status, cost and counters to `row`, and return
        the trajectory `(ts, q, p)`."""
        problem, entry, t1 = self.problem, self.entry, self.problem.t1
        repeats, budget_s = self.repeats, self.budget_s
        if isinstance(entry, SciPy):
            res, wall, n = scipy_run(problem, entry, t1, value, repeats, budget_s)
            d = problem.dim
            row.update(status=classify(res), steps=len(res.t) - 1, rejected=None,
                       wall_s=wall, compile_s=0.0, repeats=n, nfev=res.nfev)
            return res.t, res.y[:d].T, res.y[d:].T
        if isinstance(entry, Heyoka):
            from .peers import heyoka_run

            ts, q, p, fields = heyoka_run(problem, entry, t1, value, repeats, budget_s)
            row.update(fields)
            return ts, q, p
        if self.runner is None:
            max_steps = (
                entry.step_budget(int(max(self.sweep))) if isinstance(entry, Fixed)
                else self.adaptive_max_steps
            )
            self.runner = _DiffraxRunner(problem, entry, max_steps, self.saveat)
        runner = self.runner
        sol, wall, compile_s, n = _repeat(
            runner.solve, runner.arguments(t1, value), repeats, budget_s
        )
        row.update(diffrax_metrics(problem, entry, sol))
        row.update(wall_s=wall, compile_s=compile_s, repeats=n)
        return _trajectory(sol)


# -- long-time energy --------------------------------------------------------------------------
def long_time_energy(
    problem: Problem,
    runs: Sequence[tuple[Entry, float]],
    *,
    samples: int = 40,
    adaptive_max_steps: int = 2**20,
    csv_path: str | None = None,
    progress: Any = None,
    on_rows: Callable[[list[dict[str, Any]]], None] | None = None,
) -> list[dict[str, Any]]:
    """Energy error over the problem's (long) span, sampled on a logarithmic time grid.

    Each run is `(entry, value)`: a `Fixed` entry with its number of steps, or an adaptive /
    scipy entry with its `rtol`. Every step end is kept; the row for sample time `t` holds
    `energy_error`, the largest `|H − H₀|/|H₀|` over the steps up to `t` (a bounded error
    levels off, a drift keeps growing), and each row repeats the run's `wall_s` (one run after a
    compiling call on a short span), `steps` and `status`. `on_rows`, if given, is called
    with the rows of each run as it finishes.
    """
    if samples < 2:
        raise ValueError(f"samples must be at least 2, got {samples}")
    for entry, value in runs:
        _check_run(entry, value)
    energy = energy_fn(problem)
    t0, t1 = problem.t0, problem.t1
    saveat = diffrax.SaveAt(t0=True, steps=True, solver_state=True)
    rows: list[dict[str, Any]] = []
    runners: dict[tuple, _DiffraxRunner] = {}
    for entry, value in runs:
        start = len(rows)
        if progress is not None:
            progress.set_postfix_str(f"{problem.name}: {entry.name} {value:g} (long)")
        base = dict(problem=problem.name, solver=entry.name, family=entry.family,
                    parameter=entry.parameter, value=value, horizon=t1 - t0)
        try:
            if isinstance(entry, SciPy):
                res, wall, _ = scipy_run(problem, entry, t1, value, 1, 0.0)
                d = problem.dim
                ts, q, p = res.t, res.y[:d].T, res.y[d:].T
                meta = dict(status=classify(res), steps=len(ts) - 1, wall_s=wall,
                            compile_s=0.0)
            else:
                fixed = isinstance(entry, Fixed)
                max_steps = entry.step_budget(int(value)) if fixed else adaptive_max_steps
                key = (id(entry), max_steps)
                if key not in runners:  # tolerances are traced: one compilation per entry
                    runners[key] = _DiffraxRunner(problem, entry, max_steps, saveat)
                runner = runners[key]
                # compile on a short span (same shapes), then time the whole horizon
                if fixed:
                    short_t1 = t0 + (t1 - t0) / value
                    dt = jnp.asarray((t1 - t0) / value, jnp.float64)
                    short = (problem.y0, jnp.asarray(short_t1, jnp.float64), dt)
                    full = (problem.y0, jnp.asarray(t1, jnp.float64), dt)
                else:
                    short_t1 = t0 + (t1 - t0) * 1e-4
                    short = runner.arguments(short_t1, value)
                    full = runner.arguments(t1, value)
                _, compile_s = timed(runner.solve, *short)
                sol, wall = timed(runner.solve, *full)
                meta = diffrax_metrics(problem, entry, sol)
                meta.update(wall_s=wall, compile_s=compile_s)
                ts, q, p = _trajectory(sol)
            err = energy_errors(problem, energy, ts, q, p)
            envelope = np.maximum.accumulate(np.where(np.isfinite(err), err, np.inf))
            first = ts[1] if len(ts) > 1 else t1
            grid = np.geomspace(first - t0, ts[-1] - t0, samples) + t0
            index = np.clip(np.searchsorted(ts, grid, side="right") - 1, 0, len(ts) - 1)
            meta["t_end"] = float(ts[-1])
            for t, k in zip(grid, index, strict=True):
                rows.append(dict(base, **meta, t=float(t), energy_error=float(envelope[k])))
        except Exception as e:
            rows.append(dict(base, status=classify(e), message=str(e).splitlines()[0][:200]))
        if csv_path is not None:
            write_rows(rows[start:], csv_path, append=True)
        if on_rows is not None:
            on_rows(rows[start:])
        if progress is not None:
            progress.update(1)
    return rows
