"""Chord (fixed-point) iteration against Newton for the CGVI(6) step (issue 28).

1. Step cost: microseconds per constant step after compilation (median, and least, of 5
   interleaved runs) of `CGVI(6)` solved by `RoundoffNewton` and by `FixedPointIteration` (explicit
   inverse, LU solves, and with Jacobian refreshes), each at `ftol` 1 and 0 (0: until the
   updates stop shrinking), and of diffrax's `Dopri8`, on the oscillator (h = 0.5), Kepler
   with e = 0.5 (h = 2π/100) and the double pendulum (h = 0.05); iterations per step, final
   position error against the reference, ratio to Dopri8.
2. Where a step's time goes on the double pendulum: one residual, one Jacobian
   (`reduced_jacobian`), its LU factorisation, its triangular solves, a dense solve, the
   explicit inverse and a product with it, the inverse by elimination without pivoting, each
   inside a compiled loop at the second step's root; then the whole solve of that step
   from the solver's start, against the diffrax step.
3. Harder steps: the double pendulum at longer steps and a stiff quartic spring, where the
   chord iteration slows down, refreshes its Jacobian or fails.
4. The Jacobian carried from step to step: iterations of the chord iteration when each step
   uses the Jacobian at the previous step's root (what a solver state holding it would do).
5. The kinetic matrix (`matrix="kinetic"`) against the Jacobian, on the three problems and the
   outer solar system (18 coordinates).
6. Round-off by prediction (`--only predict`): the chord iteration stopped once the
   contraction of its updates predicts what is left far below one rounding unit
   (`predict=True`), against `ftol=0` and Newton, on the three problems.
7. The cheaper step, undone part by part (`--only ablation`): the default `CGVI(6)` step
   against the same step with each of its cost cuts taken back (the span as a variable
   inside optimistix, the Jacobian by per-coordinate contractions, the inverse by LAPACK,
   the state's scalars carried one by one through the loop, the loop over the unknowns as
   a pytree with its scalars one by one), one at a time and all together, in one process
   (median and least of the interleaved runs, in random order each round).

    taskset -c 1 .venv/bin/python -m benchmarks.fixed_point \\
        [--only cost|profile|hard|reuse|kinetic|predict|ablation] [--repeats 5] \\
        > benchmarks/results/fixed_point.txt
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.fixed_point import FixedPointIteration  # noqa: E402
from diffrax_vi.linalg import unpivoted_inverse  # noqa: E402
from diffrax_vi.seeding.policy import residual_scale  # noqa: E402
from diffrax_vi.step_hints import StepHints, step_options  # noqa: E402

CASES = {
    "oscillator (h = 0.5)": (problems.harmonic_oscillator, {}, 0.5, 4000),
    "Kepler e = 0.5 (h = 2π/100)": (problems.kepler, dict(eccentricity=0.5), 2 * np.pi / 100,
                                    4000),
    "double pendulum (h = 0.05)": (problems.double_pendulum, {}, 0.05, 200),
}


def root_finders():
    out = {}
    for ftol in (1.0, 0.0):
        out[f"Newton, ftol {ftol:g}"] = dvi.RoundoffNewton(ftol=ftol)
        out[f"fixed point, ftol {ftol:g}"] = FixedPointIteration(ftol=ftol)
        out[f"fixed point, LU solves, ftol {ftol:g}"] = FixedPointIteration(
            ftol=ftol, inverse=False
        )
        out[f"fixed point + refresh 0.5, ftol {ftol:g}"] = FixedPointIteration(
            ftol=ftol, refresh=0.5
        )
    return out


def _runner(problem, solver, h, n):
    variational = isinstance(solver, dvi.NetworkVI)
    term = problem.term if variational else diffrax.ODETerm(problem.term.vf)

    def run(y):
        sol = diffrax.diffeqsolve(
            term, solver, 0.0, n * h, h, y, args=problem.args, max_steps=n,
            saveat=diffrax.SaveAt(t1=True, solver_state=variational), throw=False,
        )
        its = sol.solver_state.iterations if variational else jnp.zeros((), jnp.int32)
        return sol.ys[0][-1], sol.result == diffrax.RESULTS.successful, its

    return jax.jit(run)


def _median_us(fn, arg, n, repeats, best=False):
    """Median (with `best`: least) microseconds per step of `fn` over `repeats` runs."""
    jax.block_until_ready(fn(arg))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(arg))
        times.append(time.perf_counter() - start)
    return (min(times) if best else statistics.median(times)) / n * 1e6


def _interleaved_us(runs, arg, n, repeats, best=False, shuffle=False):
    """Median (or with `best`, also the least) microseconds per step of each compiled run,
    timed in interleaved rounds (one run of each per round, with `shuffle` in a random
    order), so that a change in the machine's load touches all alike."""
    for run in runs.values():
        jax.block_until_ready(run(arg))
    times = {name: [] for name in runs}
    order = list(runs)
    rng = np.random.default_rng(0)
    for _ in range(repeats):
        if shuffle:
            rng.shuffle(order)
        for name in order:
            run = runs[name]
            start = time.perf_counter()
            jax.block_until_ready(run(arg))
            times[name].append(time.perf_counter() - start)
    median = {name: statistics.median(t) / n * 1e6 for name, t in times.items()}
    if not best:
        return median
    return median, {name: min(t) / n * 1e6 for name, t in times.items()}


def step_cost(repeats: int) -> None:
    print("step cost on constant steps, CGVI(6) (median of "
          f"{repeats} interleaved runs after compiling)")
    print("| problem | solver | us per step | / Dopri8 | least us (/ Dopri8) | "
          "iterations per step | final error |")
    print("|---|---|---|---|---|---|---|")
    for label, (make, kw, h, n) in CASES.items():
        problem = make(**kw)
        q_ref, _ = problem.reference(np.array([n * h]))
        solvers = {"Dopri8": diffrax.Dopri8()}
        solvers.update({name: dvi.CGVI(6, root_finder=rf) for name, rf in root_finders().items()})
        runs = {name: _runner(problem, solver, h, n) for name, solver in solvers.items()}
        us, least = _interleaved_us(runs, problem.y0, n, repeats, best=True)
        for name, solver in solvers.items():
            q, ok, its = jax.block_until_ready(runs[name](problem.y0))
            err = float(np.max(np.abs(np.asarray(q) - q_ref[-1])) / np.max(np.abs(q_ref[-1])))
            iters = f"{int(its) / n:.2f}" if isinstance(solver, dvi.NetworkVI) else "-"
            status = "" if bool(ok) else " (failed)"
            print(f"| {label} | {name}{status} | {us[name]:.1f} | "
                  f"{us[name] / us['Dopri8']:.2f} | {least[name]:.1f} "
                  f"({least[name] / least['Dopri8']:.2f}) | {iters} | {err:.1e} |", flush=True)


def _warm_step(problem, h):
    """The second step's projected system (context, span), its start from the first step's
    polynomial continued (as the solver seeds it) and its root."""
    solver = dvi.CGVI(6)
    form, basis, term = solver.formulation, solver.basis, problem.term
    q, p = problem.y0
    dim, dtype = q.shape[0], q.dtype

    def root(ctx, span, z0):
        options = step_options(StepHints(scale=residual_scale(ctx), jacobian=form.reduced_jacobian))
        return optx.root_find(form.reduced_residual, dvi.RoundoffNewton(ftol=0.0), z0,
                              (ctx, span), options=options, max_steps=50).value

    ctx = solver.step_context(term, 0.0, h, (q, p), problem.args)
    span = form.span(basis.zeros(dim, dtype), ctx)
    z = root(ctx, span, form.start(lambda tau: q, p, span, ctx))
    theta = basis.advance(form.expand(form.coefficients(z[0], ctx), span), 1.0)
    q1, p1 = form.projected_end_state(z, span, ctx)
    ctx = solver.step_context(term, h, 2 * h, (q1, p1), problem.args)
    q_end, dq_end = basis.value_and_derivative(theta, jnp.ones((), dtype))
    p_end = term.momentum(2 * h, q_end, dq_end / h, problem.args)
    z0 = form.start(lambda tau: basis.evaluate(theta, tau), p_end, span, ctx)
    return form, ctx, span, z0, root(ctx, span, z0)


def _loop_us(body, x0, reps=2000, repeats=5):
    """Least microseconds per call of `body` inside a compiled loop (each call depends on
    the last, so none is hoisted out of it)."""

    def looped(x):
        return jax.lax.fori_loop(0, reps, lambda i, x: body(x), x)

    return _median_us(jax.jit(looped), x0, reps, repeats, best=True)


def profile(repeats: int) -> None:
    problem = problems.double_pendulum()
    h, n = 0.05, 200
    form, ctx, span, z0, z = _warm_step(problem, h)
    args = (ctx, span)
    flat, unravel = jax.flatten_util.ravel_pytree(z)
    flat0 = jax.flatten_util.ravel_pytree(z0)[0]
    size = flat.shape[0]
    tiny = 1e-300

    def nudge(v, out):
        return v + tiny * jnp.sum(out)

    def residual_of(v):
        return jax.flatten_util.ravel_pytree(form.reduced_residual(unravel(v), args))[0]

    jac = form.reduced_jacobian(z, args)
    dim = z[1].shape[0]
    order = np.arange(size)  # the row order of `reduced_inverse`: continuity rows first
    order[:dim], order[size - dim:] = np.arange(size - dim, size), np.arange(dim)
    lu, piv = jax.scipy.linalg.lu_factor(jac)
    inv = jnp.linalg.inv(jac)
    eye = jnp.eye(size, dtype=jac.dtype)

    def solve_with(rf):
        def body(v):
            options = step_options(StepHints(scale=residual_scale(ctx),
                                             jacobian=form.reduced_jacobian))
            sol = optx.root_find(form.reduced_residual, rf, unravel(v), args, options=options,
                                 max_steps=50, throw=False)
            return nudge(v, jax.flatten_util.ravel_pytree(sol.value)[0])
        return body

    parts = {
        "residual": lambda v: nudge(v, residual_of(v)),
        "Jacobian (reduced_jacobian)": lambda v: nudge(v, form.reduced_jacobian(unravel(v),
                                                                                args)),
        "LU factorisation": lambda v: nudge(v, jax.scipy.linalg.lu_factor(jac + tiny * v[0])[0]),
        "two triangular solves (LU applied)": lambda v: nudge(
            v, jax.scipy.linalg.lu_solve((lu, piv), v)),
        "dense solve (LU + triangular solves)": lambda v: nudge(
            v, jnp.linalg.solve(jac + tiny * v[0], v)),
        "explicit inverse (LU + triangular solves with the identity)": lambda v: nudge(
            v, jax.scipy.linalg.lu_solve(jax.scipy.linalg.lu_factor(jac + tiny * v[0]), eye)),
        "product with the inverse": lambda v: nudge(v, inv @ v),
        "elimination without pivoting (unpivoted_inverse)": lambda v: nudge(
            v, unpivoted_inverse(jac + tiny * v[0], order)),
        "Jacobian and its inverse without pivoting (reduced_inverse)": lambda v: nudge(
            v, form.reduced_inverse(unravel(v), args)),
    }
    print(f"\nwhere the time goes: double pendulum, h = {h}, CGVI(6), {size} unknowns, the "
          f"second step (us per call inside a compiled loop, least of {repeats} runs)")
    print("| part | us |")
    print("|---|---|")
    for name, body in parts.items():
        print(f"| {name} | {_loop_us(body, flat, repeats=repeats):.2f} |", flush=True)
    solves = {
        "Newton, ftol 1": dvi.RoundoffNewton(ftol=1.0),
        "fixed point, ftol 1": FixedPointIteration(ftol=1.0),
        "Newton, ftol 0": dvi.RoundoffNewton(ftol=0.0),
        "fixed point, ftol 0": FixedPointIteration(ftol=0.0),
    }
    steps = {"Dopri8": diffrax.Dopri8()}
    steps.update({name: dvi.CGVI(6, root_finder=rf) for name, rf in solves.items()})
    _, step_us = _interleaved_us({name: _runner(problem, solver, h, n)
                                  for name, solver in steps.items()}, problem.y0, n, repeats,
                                 best=True)
    print(f"\nthe whole solve of that step from the solver's start, and a diffrax step (least "
          f"of {repeats} runs each)")
    print("| root finder | iterations (this step) | us per solve (this step) | "
          "us per diffrax step | rest of the step | step / Dopri8 step |")
    print("|---|---|---|---|---|---|")
    for name, rf in solves.items():
        options = step_options(StepHints(scale=residual_scale(ctx), jacobian=form.reduced_jacobian))
        its = int(optx.root_find(form.reduced_residual, rf, z0, args, options=options,
                                 max_steps=50).stats["num_steps"])
        us = _loop_us(solve_with(rf), flat0, reps=500, repeats=repeats)
        print(f"| {name} | {its} | {us:.1f} | {step_us[name]:.1f} | "
              f"{step_us[name] - us:.1f} | {step_us[name] / step_us['Dopri8']:.2f} |",
              flush=True)
    print(f"| (Dopri8) | - | - | {step_us['Dopri8']:.1f} | - | 1.00 |")


def hard(repeats: int) -> None:
    print("\nlonger steps: double pendulum over t = 10; stiff quartic spring "
          "L = v²/2 − 2500 q⁴ from q = 1 over t = 2 (median of interleaved runs)")
    print("| problem | h | solver | result | us per step | iterations per step | "
          "most in a step | restarts | final error |")
    print("|---|---|---|---|---|---|---|---|---|")
    configs = {
        "Newton, ftol 1": dvi.RoundoffNewton(ftol=1.0),
        "fixed point, ftol 1": FixedPointIteration(ftol=1.0),
        "fixed point + refresh 0.5, ftol 1": FixedPointIteration(ftol=1.0, refresh=0.5),
        "fixed point + refresh 0.1, ftol 1": FixedPointIteration(ftol=1.0, refresh=0.1),
        "fixed point, ftol 0, predict": FixedPointIteration(ftol=0.0, predict=True),
    }
    pendulum = problems.double_pendulum()
    quartic = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 2500.0 * jnp.sum(q**4))
    y_quartic = (jnp.array([1.0]), jnp.array([0.0]))
    cases = [("double pendulum", pendulum.term, pendulum.args, pendulum.y0, h, 10.0)
             for h in (0.1, 0.2, 0.5)]
    cases += [("quartic spring", quartic, None, y_quartic, h, 2.0) for h in (0.05, 0.2)]
    for label, term, args, y0, h, t1 in cases:
        n = int(round(t1 / h))
        runs = {}
        for name, rf in configs.items():
            solver = dvi.CGVI(6, root_finder=rf)

            def run(y, solver=solver, term=term, args=args, h=h, n=n):
                sol = diffrax.diffeqsolve(
                    term, solver, 0.0, n * h, h, y, args=args, max_steps=n,
                    saveat=diffrax.SaveAt(t1=True, solver_state=True), throw=False,
                )
                st = sol.solver_state
                return (sol.ys[0][-1], sol.result == diffrax.RESULTS.successful, st.iterations,
                        st.max_iterations, st.restarts)

            runs[name] = jax.jit(run)
        us = _interleaved_us(runs, y0, n, repeats)
        outs = {name: jax.block_until_ready(run(y0)) for name, run in runs.items()}
        newton_q = np.asarray(outs["Newton, ftol 1"][0])
        if label == "double pendulum":
            q_ref = pendulum.reference(np.array([n * h]))[0][-1]
            ref_note = ""
        else:  # against Newton's run (no closed form)
            q_ref, ref_note = newton_q, " (to Newton)"
        for name, (q, ok, its, most, restarts) in outs.items():
            err = float(np.max(np.abs(np.asarray(q) - q_ref)) / np.max(np.abs(q_ref)))
            print(f"| {label} | {h:g} | {name} | {'ok' if bool(ok) else 'failed'} | "
                  f"{us[name]:.1f} | {int(its) / n:.2f} | {int(most)} | {int(restarts)} | "
                  f"{err:.1e}{ref_note} |", flush=True)


def _stepper(problem, h, n, root_finder, carry_jacobian):
    """`n` constant CGVI(6) steps in a plain `lax.scan` (no diffrax), each solving the
    projected system from the previous step's polynomial continued, as the solver does.
    With `carry_jacobian`, a step's chord iteration uses the Jacobian at the previous step's
    root instead of one at its own start (what carrying it in the solver state would do).
    Returns the end position, the iterations of each step and whether any step failed."""
    solver = dvi.CGVI(6)
    form, basis, term, args = solver.formulation, solver.basis, problem.term, problem.args
    dim = problem.y0[0].shape[0]
    dtype = problem.y0[0].dtype

    def setup(t, q, p):
        ctx = solver.step_context(term, t, t + h, (q, p), args)
        return ctx, form.span(basis.zeros(dim, dtype), ctx)

    def solve(ctx, span, z0, rf, jacobian=form.reduced_jacobian):
        options = dict(scale=residual_scale(ctx), jacobian=jacobian)
        return optx.root_find(form.reduced_residual, rf, z0, (ctx, span), options=options,
                              max_steps=50, throw=False)

    def finish(sol, ctx, span):
        theta = form.expand(form.coefficients(sol.value[0], ctx), span)
        jac = form.reduced_jacobian(sol.value, (ctx, span))
        return form.projected_end_state(sol.value, span, ctx), theta, jac

    def step(carry, _):
        t, q, p, theta, jac = carry
        ctx, span = setup(t, q, p)
        theta = basis.advance(theta, 1.0)
        q_end, dq_end = basis.value_and_derivative(theta, jnp.ones((), dtype))
        p_end = term.momentum(t + h, q_end, dq_end / h, args)
        z0 = form.start(lambda tau: basis.evaluate(theta, tau), p_end, span, ctx)
        given = (lambda z, a: jac) if carry_jacobian else form.reduced_jacobian
        sol = solve(ctx, span, z0, root_finder, given)
        (q1, p1), theta, jac = finish(sol, ctx, span)
        failed = sol.result != optx.RESULTS.successful
        return (t + h, q1, p1, theta, jac), (sol.stats["num_steps"], failed)

    def run(y):
        q, p = y
        ctx, span = setup(jnp.zeros((), dtype), q, p)
        z0 = form.start(lambda tau: q, p, span, ctx)
        sol = solve(ctx, span, z0, dvi.RoundoffNewton(ftol=0.0))
        (q1, p1), theta, jac = finish(sol, ctx, span)
        carry = (jnp.asarray(h, dtype), q1, p1, theta, jac)
        (_, q, _, _, _), (its, failed) = jax.lax.scan(step, carry, None, length=n - 1)
        return q, its, jnp.any(failed)

    return jax.jit(run)


def reuse() -> None:
    print("\nJacobian carried from step to step: iterations per step of the chord iteration "
          "with the Jacobian at the previous step's root (a plain scan of CGVI(6) steps)")
    print("| problem | solver | iterations per step | most in a step | final error |")
    print("|---|---|---|---|---|")
    for label, (make, kw, h, n) in CASES.items():
        problem = make(**kw)
        q_ref, _ = problem.reference(np.array([n * h]))
        configs = {}
        for ftol in (1.0, 0.0):
            configs[f"Newton, ftol {ftol:g}"] = (dvi.RoundoffNewton(ftol=ftol), False)
            configs[f"fixed point, ftol {ftol:g}"] = (FixedPointIteration(ftol=ftol), False)
            configs[f"fixed point, previous step's Jacobian, ftol {ftol:g}"] = (
                FixedPointIteration(ftol=ftol), True)
        for name, (rf, carry) in configs.items():
            q, its, failed = jax.block_until_ready(_stepper(problem, h, n, rf, carry)(problem.y0))
            err = float(np.max(np.abs(np.asarray(q) - q_ref[-1])) / np.max(np.abs(q_ref[-1])))
            status = " (failed)" if bool(failed) else ""
            its = np.asarray(its)
            print(f"| {label} | {name}{status} | {its.mean():.2f} | {its.max()} | {err:.1e} |",
                  flush=True)


def kinetic(repeats: int) -> None:
    """The kinetic matrix against the Jacobian, on the three problems above and the outer
    solar system (18 coordinates, CGVI(7) at h = 500 days over 10^5 days)."""
    cases = dict(CASES)
    cases["outer solar system (h = 500 days)"] = (
        lambda: problems.outer_solar_system(dtype=jnp.float64), {}, 500.0, 200)
    print(f"\nkinetic matrix: us per constant step (median of {repeats} interleaved runs after "
          "compiling; ratio to Dopri8 at the same step), iterations per step, and the final "
          "position's difference to Newton's at round-off (relative)")
    print("| problem | solver | us per step | / Dopri8 | iterations per step | "
          "difference to Newton |")
    print("|---|---|---|---|---|---|")
    for label, (make, kw, h, n) in cases.items():
        problem = make(**kw)
        order = 7 if "solar" in label else 6
        finders = {
            "Newton, ftol 0": dvi.RoundoffNewton(ftol=0.0),
            "chord, ftol 0": FixedPointIteration(ftol=0.0),
            "kinetic, ftol 0": FixedPointIteration(ftol=0.0, matrix="kinetic"),
            "kinetic, ftol 1": FixedPointIteration(ftol=1.0, matrix="kinetic"),
        }
        solvers = {"Dopri8": diffrax.Dopri8()}
        solvers.update({f"CGVI({order}), {name}": dvi.CGVI(order, root_finder=rf)
                        for name, rf in finders.items()})
        runs = {name: _runner(problem, solver, h, n) for name, solver in solvers.items()}
        us = _interleaved_us(runs, problem.y0, n, repeats)
        q_newton = None
        for name, solver in solvers.items():
            q, ok, its = jax.block_until_ready(runs[name](problem.y0))
            q = np.asarray(q)
            if "Newton" in name:
                q_newton = q
            variational = isinstance(solver, dvi.NetworkVI)
            iters = f"{int(its) / n:.2f}" if variational else "-"
            diff = (f"{np.max(np.abs(q - q_newton)) / np.max(np.abs(q_newton)):.1e}"
                    if variational else "-")
            status = "" if bool(ok) else " (failed)"
            print(f"| {label} | {name}{status} | {us[name]:.1f} | "
                  f"{us[name] / us['Dopri8']:.2f} | {iters} | {diff} |", flush=True)


def predict(repeats: int) -> None:
    """Round-off by prediction (`FixedPointIteration(predict=True)`): the chord iteration run
    until the contraction of its updates predicts a remaining error far below one rounding
    unit, against running it until the updates stop shrinking (`ftol=0`) and against Newton;
    microseconds per constant `CGVI(6)` step after compiling (interleaved runs), iterations
    per step and the final position error against the problem's reference."""
    print(f"\nround-off by prediction: CGVI(6), us per step (median of {repeats} interleaved "
          "runs; ratio to Dopri8), iterations per step, final position error")
    solves = {
        "Newton, ftol 0": dvi.RoundoffNewton(ftol=0.0),
        "chord (LU), ftol 0": FixedPointIteration(ftol=0.0, inverse=False),
        "chord (LU), ftol 0, predict": FixedPointIteration(ftol=0.0, inverse=False,
                                                           predict=True),
        "Newton, ftol 1, confirm (CGVI's default before)": dvi.RoundoffNewton(ftol=1.0),
        "CGVI(6) default (chord (inverse), ftol 0, predict)": None,
    }
    print("| problem | solver | us per step | / Dopri8 | iterations per step | final error |")
    print("|---|---|---|---|---|---|")
    for label, (make, kwargs, h, n) in CASES.items():
        problem = make(**kwargs)
        steps = {"Dopri8": diffrax.Dopri8()}
        steps.update({name: dvi.CGVI(6) if rf is None else dvi.CGVI(6, root_finder=rf)
                      for name, rf in solves.items()})
        runs = {name: _runner(problem, solver, h, n) for name, solver in steps.items()}
        us = _interleaved_us(runs, problem.y0, n, repeats)
        q_ref, _ = problem.reference(np.array([n * h]))
        for name, run in runs.items():
            q, ok, its = run(problem.y0)
            err = float(np.max(np.abs(np.asarray(q) - q_ref[-1])) / np.max(np.abs(q_ref[-1])))
            iters = "-" if name == "Dopri8" else f"{int(its) / n:.2f}"
            status = "" if bool(ok) else " (failed)"
            print(f"| {label} | {name}{status} | {us[name]:.1f} | "
                  f"{us[name] / us['Dopri8']:.2f} | {iters} | {err:.1e} |", flush=True)


class _LapackStart(FixedPointIteration):
    """The chord iteration with the start's inverse by LAPACK (no hint `inverse`)."""

    def _start_factors(self, fn, y, args, options, dtype):
        jac = self._jacobian(fn, y, args, options)
        return (jnp.linalg.inv(jac.astype(dtype)),)


def _plain_loop(solver, fn, args, options, carry, limit):
    """The solve's loop carrying `carry = (y, state, aux)` as it is: each scalar of the
    state, and the start's matrix, on its own."""

    def cond(carry):
        done, _ = solver._ended(carry[1])
        return ~done & (carry[1].iterations < limit)

    def body(carry):
        return solver._update(fn, carry[0], args, options, carry[1])

    return jax.lax.while_loop(cond, body, carry)


class _ScalarsApart(FixedPointIteration):
    """The chord iteration whose loop carries the unknowns flat but the state's scalars
    (and the start's matrix) each on their own."""

    def _whole_solve_loop(self, fn, args, options, carry, limit):
        if self.refresh is not None:  # the second try's updates (as before: a pytree)
            return _plain_loop(self, fn, args, options, carry, limit)
        y, state, aux = carry
        flat, unravel = ravel_pytree(y)
        v, state, aux = _plain_loop(self, lambda v, args: fn(unravel(v), args), args,
                                    options, (flat, state, aux), limit)
        return unravel(v), state, aux


class _PytreeLoop(FixedPointIteration):
    """The chord iteration whose loop carries the unknowns as their pytree and each scalar
    of its state on its own."""

    def _whole_solve_loop(self, fn, args, options, carry, limit):
        return _plain_loop(self, fn, args, options, carry, limit)


def _per_coordinate_jacobian():
    """`VariableProjection` whose Jacobian never uses the span's sameness across
    coordinates."""
    from diffrax_vi.projection import VariableProjection

    class PerCoordinate(VariableProjection):
        @staticmethod
        def uniform_span(span):
            return False

    return PerCoordinate()


def ablation(repeats: int) -> None:
    """The default `CGVI(6)` step against itself with each cost cut undone (one at a time,
    then all), `Dopri8` alongside: microseconds per constant step (median of interleaved
    runs), ratio to `Dopri8`, iterations per step."""
    import contextlib

    import equinox as eqx

    from diffrax_vi import step_solve

    @contextlib.contextmanager
    def span_as_variable(on):
        # the projected step's functions read the span from optimistix's (traced) `args`
        saved = step_solve.with_known_span
        if on:
            step_solve.with_known_span = lambda span: (lambda args: args)
        try:
            yield
        finally:
            step_solve.with_known_span = saved

    base = dvi.CGVI(6)
    rf = base.root_finder

    def undone(*names):
        cls = {frozenset(): FixedPointIteration,
               frozenset({"inverse"}): _LapackStart,
               frozenset({"scalars"}): _ScalarsApart,
               frozenset({"loop"}): _PytreeLoop}.get(frozenset(names) - {"span", "jacobian"})
        if cls is None:  # both

            class Both(_LapackStart, _PytreeLoop):
                pass

            cls = Both
        solver = eqx.tree_at(lambda s: s.root_finder, base,
                             cls(ftol=rf.ftol, predict=rf.predict))
        if "jacobian" in names:
            solver = eqx.tree_at(lambda s: s.formulation, solver, _per_coordinate_jacobian())
        return solver, "span" in names

    variants = {
        "default CGVI(6)": undone(),
        "span as a variable inside optimistix": undone("span"),
        "Jacobian by per-coordinate contractions": undone("jacobian"),
        "inverse by LAPACK": undone("inverse"),
        "scalars carried one by one": undone("scalars"),
        "loop over the pytree of unknowns, scalars one by one": undone("loop"),
        "all undone": undone("span", "jacobian", "inverse", "loop"),
    }
    print(f"\nthe step's cost cuts undone: CGVI(6), us per step (median and least of "
          f"{repeats} interleaved runs; ratio to Dopri8's), iterations per step")
    print("| problem | variant | us per step | / Dopri8 | least us | / Dopri8's least | "
          "iterations per step |")
    print("|---|---|---|---|---|---|---|")
    for label, (make, kwargs, h, n) in CASES.items():
        problem = make(**kwargs)
        runs = {"Dopri8": _runner(problem, diffrax.Dopri8(), h, n)}
        for name, (solver, variable) in variants.items():
            run = _runner(problem, solver, h, n)
            with span_as_variable(variable):
                jax.block_until_ready(run(problem.y0))  # compiled under the variant
            runs[name] = run
        us, least = _interleaved_us(runs, problem.y0, n, repeats, best=True, shuffle=True)
        for name, run in runs.items():
            _, ok, its = run(problem.y0)
            iters = "-" if name == "Dopri8" else f"{int(its) / n:.2f}"
            status = "" if bool(ok) else " (failed)"
            print(f"| {label} | {name}{status} | {us[name]:.1f} | "
                  f"{us[name] / us['Dopri8']:.2f} | {least[name]:.1f} | "
                  f"{least[name] / least['Dopri8']:.2f} | {iters} |", flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("cost", "profile", "hard", "reuse", "kinetic",
                                           "predict", "ablation"), default=None)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    if args.only in (None, "cost"):
        step_cost(args.repeats)
    if args.only in (None, "profile"):
        profile(args.repeats)
    if args.only in (None, "hard"):
        hard(args.repeats)
    if args.only in (None, "reuse"):
        reuse()
    if args.only in (None, "kinetic"):
        kinetic(args.repeats)
    if args.only in (None, "predict"):
        predict(args.repeats)
    if args.only in (None, "ablation"):
        ablation(args.repeats)


if __name__ == "__main__":
    main()
