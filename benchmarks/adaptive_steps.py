"""The companion error estimate: calibration against the exact local error, and the work of
`diffrax.PIDController` against constant steps.

Two measurements, in one process (float64):

- **calibration**: one step from states on the reference trajectory (at three times), at
  four step sizes per problem; the step's exact local error (against the same step by
  `Dopri8` at rtol 1e-15) beside the solver's `y_error` (max norms). Printed per problem
  and solver: the ratio `|y_error| / local error` (min, median, max) over the cases whose
  local error is above rounding (> 1e-13), and the fitted order of the local error in `h`.
- **pid**: `PIDController(rtol=tol, atol=tol)` for `tol` = 1e-4 ... 1e-12, `dt0 = 0.1`;
  printed: accepted and rejected steps, the error at `t1` (max |state - reference|), the
  fewest constant steps that reach that error (a ladder of ratio 1.25, then bisection),
  and the ratio of the adaptive steps taken (accepted + rejected) to those constant steps.
- **cost** (only with `--only cost`): wall time per step attempted under `PIDController`
  (rtol 1e-10, ten times the pid span), the step with its companion, against per constant
  step of the same solver.

    .venv/bin/python -m benchmarks.adaptive_steps [--only calibration|pid|cost]
        [--problems oscillator kepler ...] [--solvers "CGVI(6)" network ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.explicit_methods import best_of  # noqa: E402
from diffrax_vi import problems  # noqa: E402

TOLERANCES = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
MAX_STEPS = 20_000
ROUNDING = 1e-13  # local errors below this are rounding, not truncation

# name: (problem, span of the pid runs, step sizes of the calibration)
PROBLEMS = {
    "oscillator": (lambda: problems.harmonic_oscillator(), 20.0, (0.5, 1.0, 2.0, 3.0)),
    "kepler": (lambda: problems.kepler(eccentricity=0.5), 2 * math.pi, (0.1, 0.2, 0.4, 0.8)),
    "double_pendulum": (lambda: problems.double_pendulum(), 10.0, (0.1, 0.2, 0.4, 0.8)),
    "henon_heiles": (lambda: problems.henon_heiles(), 20.0, (0.5, 1.0, 2.0, 3.0)),
}
SOLVERS = {
    "CGVI(4)": lambda: dvi.CGVI(4, error_estimate=True),
    "CGVI(6)": lambda: dvi.CGVI(6, error_estimate=True),
    "network": lambda: dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), error_estimate=True),
    # the companion of degree 3 for the network (before issue 63's estimate), for comparison
    "network, companion 3": lambda: dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 10), error_estimate=3
    ),
}
DEFAULT_SOLVERS = ("CGVI(4)", "CGVI(6)", "network")
CALIBRATION_TIMES = (0.0, 1.3, 2.9)
VERBOSE = False


def max_abs(a, b) -> float:
    pairs = zip(a, b, strict=True)
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in pairs)


# -- calibration --------------------------------------------------------------------------------
def exact_step_of(problem):
    """`(t0, h, y0) ↦ y(t0 + h)`: one step of `problem` by `Dopri8` at rtol 1e-15, the exact
    local solution the estimate is calibrated against."""
    @eqx.filter_jit
    def exact_step(t0, h, y0):
        sol = diffrax.diffeqsolve(
            problem.term, diffrax.Dopri8(), t0, t0 + h, h / 16, y0, args=problem.args,
            stepsize_controller=diffrax.PIDController(rtol=1e-15, atol=1e-17),
            max_steps=100_000,
        )  # fmt: skip
        return jax.tree_util.tree_map(lambda a: a[-1], sol.ys)

    return exact_step


def calibration(name: str, solver_name: str) -> None:
    make, _, steps = PROBLEMS[name]
    problem, solver = make(), SOLVERS[solver_name]()

    @eqx.filter_jit
    def one_step(t0, h, y0):
        state = solver.init(problem.term, t0, t0 + h, y0, problem.args)
        y1, y_error, _, _, result = solver.step(
            problem.term, t0, t0 + h, y0, problem.args, state, made_jump=False
        )
        return y1, y_error, result == diffrax.RESULTS.successful

    exact_step = exact_step_of(problem)

    qs, ps = problem.reference(np.asarray(CALIBRATION_TIMES))
    ratios, fits = [], []
    for t0, q, p in zip(CALIBRATION_TIMES, qs, ps, strict=True):
        y0 = (jnp.asarray(q), jnp.asarray(p))
        t0 = jnp.asarray(t0)
        errors = []
        for h in steps:
            y1, y_error, ok = one_step(t0, jnp.asarray(h), y0)
            if not bool(ok):
                errors.append(math.nan)
                continue
            local = max_abs(y1, exact_step(t0, jnp.asarray(h), y0))
            estimate = max(float(jnp.max(jnp.abs(e))) for e in y_error)
            errors.append(local)
            if VERBOSE:
                print(f"    t0 {float(t0):4.1f} h {h:5.2f} local {local:9.2e} estimate "
                      f"{estimate:9.2e} ratio {estimate / max(local, 1e-300):6.2f}")
            if local > ROUNDING:
                ratios.append(estimate / local)
        good = [(h, e) for h, e in zip(steps, errors, strict=True) if e > ROUNDING]
        if len(good) >= 2:
            (h_a, e_a), (h_b, e_b) = good[0], good[-1]
            fits.append(math.log(e_b / e_a) / math.log(h_b / h_a))
    if ratios:
        r = np.asarray(ratios)
        summary = (f"ratio min {r.min():.2f} median {np.median(r):.2f} max {r.max():.2f} "
                   f"over {r.size} steps")
    else:
        summary = "no step's local error above rounding"
    order = f"local order in h {np.median(fits):.1f}" if fits else "order: -"
    print(f"  {name:16s} {solver_name:22s} error_order {solver.error_order(problem.term):3d}  "
          f"{summary}; {order}", flush=True)


# -- pid against constant steps -------------------------------------------------------------------
def pid_table(name: str, solver_name: str) -> list[dict]:
    make, t1, _ = PROBLEMS[name]
    problem, solver = make(), SOLVERS[solver_name]()
    constant_solver = dataclasses.replace(solver, error_estimate=None)
    q_ref, p_ref = problem.reference(np.array([t1]))

    def error(sol) -> float:
        return max_abs((sol.ys[0][-1], sol.ys[1][-1]), (q_ref[0], p_ref[0]))

    @eqx.filter_jit
    def adaptive(tol):
        return diffrax.diffeqsolve(
            problem.term, solver, 0.0, t1, 0.1, problem.y0, args=problem.args,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            saveat=diffrax.SaveAt(t1=True), max_steps=MAX_STEPS, throw=False,
        )  # fmt: skip

    @eqx.filter_jit
    def constant(dt):
        return diffrax.diffeqsolve(
            problem.term, constant_solver, 0.0, t1, dt, problem.y0, args=problem.args,
            saveat=diffrax.SaveAt(t1=True), max_steps=MAX_STEPS, throw=False,
        )  # fmt: skip

    cache: dict[int, float] = {}

    def constant_error(n: int) -> float:
        if n not in cache:
            sol = constant(jnp.asarray(t1 / n))
            ok = sol.result == diffrax.RESULTS.successful
            cache[n] = error(sol) if bool(ok) else math.inf
        return cache[n]

    def fewest_constant_steps(target: float, start: int) -> int | None:
        """The fewest constant steps whose error is at most `target`: up a ladder of ratio
        1.25 from `start`, then bisection below the first count that reaches it."""
        low, n = 0, max(1, start)
        while constant_error(n) > target:
            low, n = n, math.ceil(n * 1.25)
            if n > MAX_STEPS:
                return None
        if low == 0:  # reached at the start: walk down the ladder first
            while n > 1 and constant_error(max(1, math.floor(n / 1.25))) <= target:
                n = max(1, math.floor(n / 1.25))
            low = max(0, math.floor(n / 1.25))
        while n - low > 1:
            mid = (low + n) // 2
            if constant_error(mid) <= target:
                n = mid
            else:
                low = mid
        return n

    rows = []
    for tol in TOLERANCES:
        start = time.perf_counter()
        sol = adaptive(jnp.asarray(tol))
        jax.block_until_ready(sol.ys)
        seconds = time.perf_counter() - start
        accepted = int(sol.stats["num_accepted_steps"])
        rejected = int(sol.stats["num_rejected_steps"])
        ok = bool(sol.result == diffrax.RESULTS.successful)
        err = error(sol) if ok else math.inf
        n_const = fewest_constant_steps(err, accepted // 2) if ok else None
        ratio = (accepted + rejected) / n_const if n_const else math.nan
        rows.append(dict(tol=tol, accepted=accepted, rejected=rejected, error=err,
                         constant=n_const, ratio=ratio, ok=ok, seconds=seconds))
        print(f"  {name:16s} {solver_name:22s} rtol {tol:.0e}  steps {accepted:5d} + "
              f"{rejected:3d} rejected  error {err:9.2e}  constant steps "
              f"{n_const if n_const else '-':>6}  ratio {ratio:5.2f}"
              f"{'' if ok else '  (failed: ' + str(sol.result) + ')'}", flush=True)
    errors = [r["error"] for r in rows]
    monotone = all(b < a for a, b in zip(errors, errors[1:], strict=False))
    print(f"  {name:16s} {solver_name:22s} error decreasing with rtol: {monotone}; ratio at "
          f"1e-12: {rows[-1]['ratio']:.2f}", flush=True)
    return rows


# -- cost ---------------------------------------------------------------------------------------
def cost(name: str, solver_name: str, tol: float = 1e-10) -> None:
    """Wall time per step attempted under `PIDController(rtol=atol=tol)` (the step and its
    companion) against per step of the same solver at constant steps, as many as the
    adaptive run accepted, over ten times the pid span (so that a solve's fixed cost is
    small against its steps)."""
    make, t1, _ = PROBLEMS[name]
    t1 = 10 * t1
    problem, solver = make(), SOLVERS[solver_name]()
    constant_solver = dataclasses.replace(solver, error_estimate=None)

    @eqx.filter_jit
    def adaptive():
        return diffrax.diffeqsolve(
            problem.term, solver, 0.0, t1, 0.1, problem.y0, args=problem.args,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            saveat=diffrax.SaveAt(t1=True), max_steps=MAX_STEPS, throw=False,
        )  # fmt: skip

    sol = adaptive()
    accepted = int(sol.stats["num_accepted_steps"])
    taken = accepted + int(sol.stats["num_rejected_steps"])

    @eqx.filter_jit
    def constant():
        return diffrax.diffeqsolve(
            problem.term, constant_solver, 0.0, t1, t1 / accepted, problem.y0,
            args=problem.args, saveat=diffrax.SaveAt(t1=True), max_steps=MAX_STEPS,
            throw=False,
        )  # fmt: skip

    per_adaptive = best_of(lambda: adaptive().ys, 3) / taken * 1e3
    per_constant = best_of(lambda: constant().ys, 3) / accepted * 1e3
    print(f"  {name:16s} {solver_name:22s} rtol {tol:.0e}: {taken} steps attempted, "
          f"{per_adaptive:.3f} ms each with the estimate; constant {accepted} steps "
          f"{per_constant:.3f} ms each; ratio {per_adaptive / per_constant:.1f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=("calibration", "pid", "cost"))
    parser.add_argument("--problems", nargs="+", choices=tuple(PROBLEMS), default=tuple(PROBLEMS))
    parser.add_argument("--solvers", nargs="+", choices=tuple(SOLVERS), default=DEFAULT_SOLVERS)
    parser.add_argument("--verbose", action="store_true", help="each calibration step")
    args = parser.parse_args()
    global VERBOSE
    VERBOSE = args.verbose
    if args.only in (None, "calibration"):
        print("calibration: |y_error| / exact local error of one step (max norms), steps from "
              f"t = {CALIBRATION_TIMES} on the reference, local errors > {ROUNDING:g}")
        for name in args.problems:
            print(f"{name}: h = {PROBLEMS[name][2]}")
            for solver_name in args.solvers:
                calibration(name, solver_name)
    if args.only in (None, "pid"):
        print("pid: PIDController(rtol=tol, atol=tol), dt0 = 0.1; error max |state - reference| "
              "at t1; ratio = (accepted + rejected) / fewest constant steps reaching that error")
        for name in args.problems:
            print(f"{name}: t1 = {PROBLEMS[name][1]:g}")
            for solver_name in args.solvers:
                pid_table(name, solver_name)
    if args.only == "cost":
        print("cost: wall time per step, best of 3, one process")
        for name in args.problems:
            for solver_name in args.solvers:
                cost(name, solver_name)


if __name__ == "__main__":
    main()
