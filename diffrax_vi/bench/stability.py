"""The reference's numerical-stability sweep (problems_and_benchmarks §2) for `NetworkVI`.

Each case integrates exactly `steps` (10) steps of size `dt` over `(0, steps·dt)` in one working
precision and records, as the reference's benchmark does:

- `status` (`classify`; `maxiter` and failures count as not converged),
- `ref_err`: relative max-norm error of the final `q` against the problem's float64 reference
  (closed form, stored, or DOP853 at `rtol = 1e-13`; the reference used Gauss(8) at the
  smallest `dt`),
- `ham_drift`: `max_n |H_n − H_0| / |H_0|` over the step ends, evaluated in float64,
- `iterations`: nonlinear iterations of the final step, and `total_s`: wall time of the run
  including compilation (cases that differ only in `dt`, λ or the convergence test share one
  compilation),
- `result`: the `diffrax.RESULTS` member the solve ended with, and `err_t1`: the error of the
  final `q` relative to the size of the motion, `max|q(t1) − q_ref(t1)| / max_n |q_ref(t_n)|`
  (`ref_err` divides by `|q_ref(t1)|` alone, which is small where the motion crosses zero).

What the rows say (the restated stability target, convergence rates) is read by
`diffrax_vi.bench.stability_results`.

The reference's "DogLeg" and "Newton/Backtracking" solvers map to our `LevenbergMarquardt`
(a trust-region-like damped Gauss–Newton, with its own damping scale) and `RegularisedNewton`
(the reference's `J + λI` Newton with Armijo backtracking, `λ = 16·sqrt(eps(T))` by default).
One more solver, `"projection"`, is none of the reference's: the projected step
(`formulation=VariableProjection()` with its `RoundoffNewton`, undamped, so `λ = 0`), which has
only our convergence test. It is not in the default grids (which are the reference's); ask for
it with `quick_grid(solvers=...)` or `python -m diffrax_vi.bench stability --solvers projection`.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Iterable, Sequence
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import problems as _problems
from .._activations import elu, gelu, relu_k, tanh
from .._ansatz.shallow import ShallowNetBasis
from .._quadrature import GaussLegendre
from .._root_finder.damped_newton import LevenbergMarquardt, RegularisedNewton
from .._root_finder.newton import RoundoffNewton
from .._seeding.policy import SeedPolicy
from .._seeding.trajectories import HermiteExtrapolation, IntegratorExtrapolation, NoExtrapolation
from .._solver import NetworkVI
from .._step.projection import VariableProjection
from .._step_size import RetryFailedSteps
from .executor import run_sweep
from .harness import relative_error
from .rows import write_rows
from .status import classify, result_name

__all__ = [
    "StabilityCase",
    "quick_grid",
    "full_grid",
    "run_case",
    "stability_sweep",
    "StabilitySweep",
    "SOLVERS",
    "PROJECTED",
    "select_solvers",
]

ACTIVATIONS = {
    "gelu": gelu,
    "tanh": tanh,
    "elu": elu,
    "relu2": relu_k(2),
    "relu3": relu_k(3),
    "relu4": relu_k(4),
}
INITIAL_GUESSES = {
    # the reference's grid, so its sub-step count too (explicit, whatever our default)
    "midpoint": lambda: IntegratorExtrapolation(substeps=10),
    "hermite": HermiteExtrapolation,
    "previous": NoExtrapolation,
}
# The all-parameter solves' root finders (the reference's two solvers)...
DAMPED = {"LevenbergMarquardt": LevenbergMarquardt, "RegularisedNewton": RegularisedNewton}
# ...and the projected step: `VariableProjection()` on its default hidden layer, solved by
# `NetworkVI`'s default root finder for it (`RoundoffNewton`, taking the Jacobian-free
# iteration where the kinetic matrix is constant; no λ, no reference convergence test).
PROJECTED = {"projection": RoundoffNewton}
SOLVERS = {**DAMPED, **PROJECTED}
PROBLEMS = {
    "harmonic_oscillator": _problems.harmonic_oscillator,
    "pendulum": _problems.pendulum,
    "double_pendulum": _problems.double_pendulum,
    "toda_lattice": _problems.toda_lattice,
}
# diffeqsolve's step budget for a run under RetryFailedSteps (each failed trial and each
# piece counts: 10 intervals of up to 2^8 pieces, and the failures on the way).
RETRY_MAX_STEPS = 4096
CONTROLLERS = ("constant", "retry", "pid")
# The adaptive runs' tolerance (`controller="pid"`): rtol = atol = sqrt(eps) of the precision.
PID_TOLERANCE_POWER = 0.5


def pid_tolerance(dtype: str) -> float:
    """`rtol = atol` of a case under `PIDController` with the error estimate."""
    return float(np.finfo(np.dtype(dtype)).eps) ** PID_TOLERANCE_POWER

# Per-problem quick settings of the reference (§2.3): network width S and quadrature nodes R.
QUICK_WIDTH = {"harmonic_oscillator": 10, "pendulum": 8, "double_pendulum": 10, "toda_lattice": 8}
QUICK_NODES = {"harmonic_oscillator": 8, "pendulum": 8, "double_pendulum": 16, "toda_lattice": 16}


@dataclasses.dataclass(frozen=True)
class StabilityCase:
    """One case of the sweep.

    **Fields:** `problem` (a key of `PROBLEMS`), `dt`, `dtype` (`"float16"`, `"float32"`,
    `"float64"`), `nodes` (Gauss–Legendre nodes R), `width` (S), `activation` (a key of
    `ACTIVATIONS`), `solver` (a key of `SOLVERS`; `"projection"` is the projected step,
    `VariableProjection()`), `lam` (see `lam_value`), `initial_guess` (a key of
    `INITIAL_GUESSES`; the projected step's default hidden layer starts each step from the
    previous curve, so it does not use it), `steps` (10), `max_iterations` (the per-step
    iteration cap), `acceptance` (`"strict"`: our convergence test, or `"reference"`: the
    reference's, see `AbstractDampedNewton`'s `convergence`; the projected step has only
    `"strict"`), `controller` (`"constant"`: exactly `steps` steps, `StepTo`; `"retry"`: the
    same grid under `RetryFailedSteps`, which splits a failed step into pieces; or `"pid"`:
    from the same first step, `PIDController` at `pid_tolerance` with the solver's error
    estimate, `error_estimate=True`).
    """

    problem: str
    dt: float
    dtype: str
    nodes: int
    width: int
    activation: str
    solver: str
    lam: float | None = None
    initial_guess: str = "midpoint"
    steps: int = 10
    max_iterations: int = 100
    acceptance: str = "strict"
    controller: str = "constant"

    def __post_init__(self):
        for field, table in (("problem", PROBLEMS), ("activation", ACTIVATIONS),
                             ("solver", SOLVERS), ("initial_guess", INITIAL_GUESSES)):
            if getattr(self, field) not in table:
                raise ValueError(
                    f"unknown {field} {getattr(self, field)!r}; choose from {sorted(table)}"
                )
        if self.dtype not in ("float16", "float32", "float64"):
            raise ValueError(f"dtype must be float16, float32 or float64; got {self.dtype!r}")
        if self.acceptance not in ("strict", "reference"):
            raise ValueError(f"acceptance must be strict or reference; got {self.acceptance!r}")
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller must be one of {CONTROLLERS}; got {self.controller!r}")
        if self.solver in PROJECTED and self.acceptance != "strict":
            raise ValueError(
                f"the {self.solver!r} solver has only our convergence test (acceptance "
                f"'strict'), got acceptance {self.acceptance!r}"
            )
        if self.solver in PROJECTED and self.lam not in (None, 0, 0.0):
            raise ValueError(f"the {self.solver!r} solver is undamped (λ = 0), got lam={self.lam}")
        if not self.dt > 0 or self.steps < 1 or self.max_iterations < 1:
            raise ValueError(f"dt, steps and max_iterations must be positive: {self!r}")

    @property
    def lam_value(self) -> float:
        """λ: the given one; else, for `RegularisedNewton`, the reference's `16·sqrt(eps(T))`
        (its `regularization_factor`, the shift of `J + λI`), and for `LevenbergMarquardt`
        its own default damping scale (`μ = λ‖F‖`: a different quantity, which the
        reference's DogLeg has no counterpart of); 0 for the projected step's undamped Newton."""
        if self.solver in PROJECTED:
            return 0.0
        if self.lam is not None:
            return self.lam
        if self.solver == "LevenbergMarquardt":
            return float(LevenbergMarquardt.lam)
        return float(16 * np.sqrt(np.finfo(np.dtype(self.dtype)).eps))

    def solver_key(self) -> tuple:
        """Cases with equal keys share one compilation (they differ only in `dt`, λ or the
        convergence test, which enter the compiled solve as traced values)."""
        return (self.problem, self.dtype, self.nodes, self.width, self.activation,
                self.solver, self.initial_guess, self.steps, self.max_iterations,
                self.controller)

    def build(self, reference=None, lam=None) -> NetworkVI:
        """The configured `NetworkVI`. `reference` (a possibly traced boolean) overrides
        `acceptance`, and `lam` (a possibly traced scalar) `lam_value`, so that cases that
        differ only in them share one compiled program."""
        if self.solver in PROJECTED:
            return NetworkVI(
                ShallowNetBasis(ACTIVATIONS[self.activation], self.width),
                GaussLegendre(self.nodes),
                seed=SeedPolicy(initial_trajectory=INITIAL_GUESSES[self.initial_guess]()),
                formulation=VariableProjection(),
                root_finder=None,  # the default step's
                root_find_max_steps=self.max_iterations,
                error_estimate=True if self.controller == "pid" else None,
            )
        lam = self.lam_value if lam is None else lam
        if reference is None:
            root_finder = SOLVERS[self.solver](lam=lam, convergence=self.acceptance)
        else:
            root_finder = _SWITCHED[self.solver](lam=lam, reference=reference)
        return NetworkVI(
            ShallowNetBasis(ACTIVATIONS[self.activation], self.width),
            GaussLegendre(self.nodes),
            seed=SeedPolicy(initial_trajectory=INITIAL_GUESSES[self.initial_guess]()),
            root_finder=root_finder,
            root_find_max_steps=self.max_iterations,
            error_estimate=True if self.controller == "pid" else None,
        )


def quick_grid(
    problems: Sequence[str] = ("harmonic_oscillator", "pendulum", "double_pendulum"),
    *,
    dts: Sequence[float] = (0.1, 1.0, 10.0),
    dtypes: Sequence[str] = ("float64", "float32", "float16"),
    activations: Sequence[str] = ("gelu", "tanh"),
    solvers: Sequence[str] = ("LevenbergMarquardt", "RegularisedNewton"),
    max_iterations: int = 1000,
    acceptances: Sequence[str] = ("strict", "reference"),
    retry_dts: Sequence[float] = (1.0, 10.0),
    pid_dts: Sequence[float] = (10.0,),
) -> list[StabilityCase]:
    """The reference's quick grid: 3 dt × 3 precisions × 2 activations × 2 solvers per problem
    (36 cases), with its per-problem S and R, λ = 16·sqrt(eps(T)) for `RegularisedNewton`,
    the midpoint guess and its iteration cap (1000); run once per convergence test in
    `acceptances` (ours, and the reference's, so that rates compare like with like). A
    solver of `PROJECTED` (`"projection"`) runs with our test only.

    The cases with our test and a `dt` in `retry_dts` (default: dt = 1 and 10) run once more
    under `RetryFailedSteps` (`"retry"`), and those with a `dt` in `pid_dts` (default: 10)
    under `PIDController` with the error estimate (`"pid"`), one more compilation each per
    network, precision and solver: whether each reaches `t1`, and how accurately
    (`stability_target`)."""
    cases = [
        StabilityCase(p, dt, T, QUICK_NODES[p], QUICK_WIDTH[p], a, s,
                      max_iterations=max_iterations, acceptance=acc)
        for acc, p, T, a, s, dt in itertools.product(
            acceptances, problems, dtypes, activations, solvers, dts)
        if not (s in PROJECTED and acc != "strict")
    ]
    return cases + [dataclasses.replace(c, controller=controller)
                    for controller, dts in (("retry", retry_dts), ("pid", pid_dts))
                    for c in cases if c.acceptance == "strict" and c.dt in dts]


def full_grid(
    problems: Sequence[str] = ("harmonic_oscillator", "pendulum", "double_pendulum",
                               "toda_lattice"),
    max_iterations: int = 1000,
    solvers: Sequence[str] = ("LevenbergMarquardt", "RegularisedNewton"),
) -> list[StabilityCase]:
    """The reference's full grid: dt ∈ {0.01, 0.1, 1, 10} × 3 precisions × R ∈ {4, 8, 16} ×
    S ∈ {4, 6, 8} × 6 activations × 2 solvers × λ ∈ {0, 1e-7, 1e-5, 1e-3, 16·sqrt(eps)} ×
    3 initial guesses. λ is `RegularisedNewton`'s shift; `LevenbergMarquardt` runs once,
    with its own damping (11 664 cases per problem; hours). The projected step
    (`"projection"`, when in `solvers`) runs once per network and dt, with the midpoint
    guess only: its hidden layer is fixed and its steps start from the previous curve, so λ
    and the initial guess do not enter (648 cases per problem, 162 compilations)."""
    _check_solvers(solvers)
    lams = (0.0, 1e-7, 1e-5, 1e-3, None)
    chosen = []
    for sv in solvers:
        if sv == "RegularisedNewton":
            chosen += [(sv, lam, g) for lam in lams for g in INITIAL_GUESSES]
        elif sv in PROJECTED:
            chosen.append((sv, None, "midpoint"))
        else:
            chosen += [(sv, None, g) for g in INITIAL_GUESSES]
    # order of the reference's product: solver, then λ, then initial guess
    return [
        StabilityCase(p, dt, T, r, s, a, sv, lam, g, max_iterations=max_iterations)
        for p, T, r, s, a, (sv, lam, g), dt in itertools.product(
            problems, ("float64", "float32", "float16"), (4, 8, 16), (4, 6, 8), ACTIVATIONS,
            chosen, (0.01, 0.1, 1.0, 10.0),
        )
    ]


def _check_solvers(solvers: Sequence[str]) -> None:
    unknown = [s for s in solvers if s not in SOLVERS]
    if unknown:
        raise ValueError(f"unknown solver(s) {unknown}; choose from {sorted(SOLVERS)}")


def select_solvers(patterns: Sequence[str] | None) -> tuple[str, ...]:
    """The sweep's solvers named by the command line's `--solvers` (substrings of the keys of
    `SOLVERS`, as the work-precision study matches its entry names); `None` or empty: the
    reference's two. Raises `ValueError` when a pattern matches no solver."""
    if not patterns:
        return tuple(DAMPED)
    missing = [p for p in patterns if not any(p in name for name in SOLVERS)]
    if missing:
        raise ValueError(
            f"--solvers {missing} match(es) no stability solver; choose from {sorted(SOLVERS)}"
        )
    return tuple(name for name in SOLVERS if any(p in name for p in patterns))


def _switched(base: type) -> type:
    """`base` with the convergence test chosen by a (possibly traced) field `reference`."""

    class Switched(base):
        reference: Any = False

        def _reference_mode(self):
            return self.reference

    Switched.__name__ = Switched.__qualname__ = f"_Switched{base.__name__}"
    return Switched


_SWITCHED = {name: _switched(cls) for name, cls in DAMPED.items()}


class _Compiled:
    """A compiled 10-step solve for one `solver_key`; `dt` enters through `StepTo`'s times,
    the convergence test as a traced flag and λ as a traced scalar. Under `"retry"` and
    `"pid"` the solve runs from `ts[0]` to `ts[-1]` from a first step of `ts[1] − ts[0]`
    with `RetryFailedSteps` or `PIDController`, and saves the end state only."""

    def __init__(self, case: StabilityCase):
        self.problem = PROBLEMS[case.problem](dtype=np.dtype(case.dtype))
        term, args = self.problem.term, self.problem.args
        steps = case.steps

        retry = case.controller == "retry"
        pid = case.controller == "pid"
        tolerance = pid_tolerance(case.dtype)

        @eqx.filter_jit
        def solve(y0, ts, reference, lam):
            solver = case.build(reference=reference, lam=lam)
            if retry or pid:
                controller = (RetryFailedSteps() if retry
                              else diffrax.PIDController(rtol=tolerance, atol=tolerance))
                dt0, max_steps = ts[1] - ts[0], RETRY_MAX_STEPS
                saveat = diffrax.SaveAt(t1=True, solver_state=True)
            else:
                dt0, controller, max_steps = None, diffrax.StepTo(ts), steps
                saveat = diffrax.SaveAt(t0=True, steps=True, solver_state=True)
            return diffrax.diffeqsolve(
                term, solver, ts[0], ts[-1], dt0, y0, args=args, saveat=saveat,
                stepsize_controller=controller, max_steps=max_steps, throw=False,
            )

        self.solve = solve

        def energy(ts, qs, ps):
            return jax.vmap(lambda t, q, p: self.problem.energy(t, q, p))(ts, qs, ps)

        self.energy = jax.jit(energy)


def run_case(case: StabilityCase, cache: dict | None = None) -> dict[str, Any]:
    """Run one case (never raises: an exception becomes status `error:<Name>`)."""
    row: dict[str, Any] = dataclasses.asdict(case)
    row["lam"] = case.lam_value
    start = time.perf_counter()
    try:
        cache = {} if cache is None else cache
        key = case.solver_key()
        if key not in cache:
            cache.clear()  # keep one compiled solve alive at a time
            cache[key] = _Compiled(case)
        compiled = cache[key]
        problem = compiled.problem
        dtype = np.dtype(case.dtype)
        ts64 = problem.t0 + case.dt * np.arange(case.steps + 1, dtype=np.float64)
        reference = jnp.asarray(case.acceptance == "reference")
        sol = jax.block_until_ready(
            compiled.solve(problem.y0, jnp.asarray(ts64, dtype), reference,
                           jnp.asarray(case.lam_value, jnp.float64)))
        row["total_s"] = time.perf_counter() - start
        row["status"] = classify(sol, iteration_cap=case.max_iterations)
        row["result"] = result_name(sol.result)
        state = sol.solver_state
        row["iterations"] = int(state.last_iterations)
        if case.controller in ("retry", "pid"):
            _retry_columns(row, sol, problem, ts64)
            return row
        row["steps_done"] = int(state.steps)
        ts = np.asarray(sol.ts)
        keep = np.isfinite(ts)
        qs, ps = (np.asarray(x, np.float64)[keep] for x in sol.ys)
        if row["status"] in ("ok", "maxiter") and keep.sum() == case.steps + 1:
            q_ref = problem.reference(ts64[-1:])[0][0]
            row["ref_err"] = relative_error(qs[-1], q_ref)
            row["err_t1"] = _motion_error(qs[-1], problem, ts64)
            f64 = jnp.float64
            h = np.asarray(compiled.energy(jnp.asarray(ts64, f64), jnp.asarray(qs, f64),
                                           jnp.asarray(ps, f64)))
            row["ham_drift"] = float(np.max(np.abs(h - h[0])) / abs(h[0]))
    except Exception as e:  # every case is isolated
        row["total_s"] = time.perf_counter() - start
        row["status"] = classify(e)
        row["message"] = str(e).splitlines()[0][:200] if str(e) else ""
    return row


def _motion_error(q: np.ndarray, problem, ts64: np.ndarray) -> float:
    """`max|q − q_ref(t1)| / max_n |q_ref(t_n)|` over the case's grid `ts64` (`err_t1`)."""
    q_refs = np.asarray(problem.reference(ts64)[0], np.float64)
    scale = float(np.max(np.abs(q_refs)))
    err = float(np.max(np.abs(np.asarray(q, np.float64) - q_refs[-1])))
    return err / scale if scale > 0 else err


def _retry_columns(row: dict, sol, problem, ts64: np.ndarray) -> None:
    """The columns of a run under `RetryFailedSteps`: `t_end` (the time it ended at),
    `reached` (a successful result with a finite state at `t1`), `steps_done` (accepted
    steps and pieces), `rejected` (failed trials), `err_t1` where the end state is finite,
    and `ham_drift` there (the energy error at `t1` only: no other state is saved)."""
    t_end = float(np.asarray(sol.ts)[-1])
    q, p = (np.asarray(x, np.float64)[-1] for x in sol.ys)
    finite = bool(np.all(np.isfinite(q)) and np.all(np.isfinite(p)))
    row["t_end"] = t_end
    row["reached"] = bool(row["result"] == "successful" and finite
                          and abs(t_end - ts64[-1]) <= 1e-6 * max(abs(ts64[-1]), 1.0))
    row["steps_done"] = int(sol.stats["num_accepted_steps"])
    row["rejected"] = int(sol.stats["num_rejected_steps"])
    if finite:
        row["err_t1"] = _motion_error(q, problem, ts64)
        f64 = jnp.float64
        h0 = float(problem.energy(f64(ts64[0]), *(jnp.asarray(x, f64) for x in problem.y0)))
        h1 = float(problem.energy(f64(t_end), jnp.asarray(q, f64), jnp.asarray(p, f64)))
        row["ham_drift"] = abs(h1 - h0) / abs(h0)


SWEEP_COLUMNS = (
    "problem", "dt", "dtype", "nodes", "width", "activation", "solver", "lam", "initial_guess",
    "steps", "max_iterations", "acceptance", "controller", "status", "result", "ref_err",
    "err_t1", "ham_drift", "iterations", "steps_done", "rejected", "reached", "t_end",
    "total_s", "message",
)


@dataclasses.dataclass(frozen=True)
class StabilitySweep:
    """The stability cases as a sweep of `diffrax_vi.bench.executor.run_sweep`: a case's id
    names every field, and the cases of one `solver_key` share one compiled solve."""

    name: str = "stability"

    def case_id(self, case: StabilityCase) -> str:
        return "|".join(f"{f.name}={getattr(case, f.name)!r}"
                        for f in dataclasses.fields(case))

    def config_key(self, case: StabilityCase) -> tuple:
        return case.solver_key()

    def run(self, cases: Sequence[StabilityCase], cache: dict, emit) -> None:
        for case in cases:
            emit(self.case_id(case), [run_case(case, cache)])


def stability_sweep(
    cases: Iterable[StabilityCase],
    *,
    csv_path: str | None = None,
    progress: Any = None,
    executor: Any = None,
    log: str | None = None,
    resume: bool = False,
    batch_size: int | None = None,
) -> list[dict[str, Any]]:
    """Run every case (grouped so that cases sharing a compilation run together), appending
    each row to `csv_path` as soon as it is measured; the CSV is rewritten in case order at
    the end. `progress` is a tqdm-like object.

    `executor` (a `SerialExecutor`, the default, or a `DaskExecutor`) runs the cases; `log`
    is a result log (`executor.ResultLog`) that every finished case is appended to, and with
    `resume` the cases already in it are not run again; `batch_size` caps the cases of one
    configuration in one task (see `run_sweep`). The rows are the same whatever runs them
    (`total_s` aside, a wall time)."""
    cases = sorted(cases, key=lambda c: (repr(c.solver_key()), c.acceptance, c.dt))
    if csv_path is not None:
        write_rows([], csv_path, columns=SWEEP_COLUMNS)

    def stream(case_id, rows):
        if csv_path is not None:
            write_rows(rows, csv_path, append=True, columns=SWEEP_COLUMNS)

    rows = run_sweep(StabilitySweep(), cases, executor=executor, log=log, resume=resume,
                     progress=progress, on_case=stream, batch_size=batch_size)
    if csv_path is not None:
        write_rows(rows, csv_path, columns=SWEEP_COLUMNS)
    return rows

