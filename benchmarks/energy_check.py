"""The energy check's measurements: how far the energy of one step moves on correct steps at
large step sizes, and on steps that converged to a wrong root.

For each problem, solver and constant step `h` (float64): a constant-step solve with the
check off (`energy_check=False`), saving every step; for each step its relative energy jump
`|H₁ − H₀| / (|p₀·v₀| + |L₀|)` (what the solver's energy check bounds) and its local error,
the distance of its end state from a Dopri8 solve (rtol 1e-12) of the same interval from the
same start, relative to `1 + max|y₀|`. A step is *correct* where that local error is below
`--wrong` (default 0.05), else *wrong*. Printed per case: the steps taken, the result, the
largest jump of the correct steps, the smallest jump of the wrong ones, the largest local
error, and the three largest jumps with their local errors. `--cost N` times the check
instead (Kepler, `CGVI(6)` and the network of the same span, N alternated runs) and counts
the HLO instructions of a 10-step solve and the kernels a step launches; `--runs` solves
the elastic pendulum to t = 20 with the check off and on (constant steps, `RetryFailedSteps`).

    .venv/bin/python -m benchmarks.energy_check [--only elastic] [--solvers "CGVI(6)" ...]
    .venv/bin/python -m benchmarks.energy_check --cost 31   # the check's cost on Kepler
    .venv/bin/python -m benchmarks.energy_check --runs      # the elastic pendulum's runs
"""

from __future__ import annotations

import argparse
import math

import numpy as np


def _elastic_pendulum():
    import jax.numpy as jnp

    import diffrax_vi as dvi

    def lagrangian(t, q, v, args):
        stretch = jnp.sqrt(q @ q) - 1.0
        return 0.5 * v @ v - 0.5 * 400.0 * stretch**2 - 9.81 * q[1]

    y0 = (jnp.array([1.05, 0.0]), jnp.array([0.0, 0.5]))
    return dvi.LagrangianTerm(lagrangian), y0, None, 20.0


def cases():
    """`name -> (term, y0, args, t1, step sizes)`."""
    from diffrax_vi import problems

    out = {}
    ho = problems.harmonic_oscillator()  # period 2π/√0.5 ≈ 8.9
    out["oscillator"] = (ho.term, ho.y0, ho.args, 40.0, (2.0, 4.0, 8.0))
    kepler = problems.kepler(eccentricity=0.5)  # period 2π
    out["kepler"] = (kepler.term, kepler.y0, kepler.args, 20.0, (0.5, 1.0, 2.0))
    dp = problems.double_pendulum()
    out["double_pendulum"] = (dp.term, dp.y0, dp.args, 10.0, (0.1, 0.3, 0.6))
    term, y0, args, t1 = _elastic_pendulum()  # spring period 2π/20 ≈ 0.31
    out["elastic"] = (term, y0, args, t1, (0.05, 0.2, 0.6, 0.94))
    return out


def solvers(check: bool):
    import diffrax_vi as dvi

    chord = dvi.ChordIteration(ftol=0.0, predict=True, picard=False)
    return {
        "CGVI(2)": dvi.CGVI(2, energy_check=check),
        "CGVI(4)": dvi.CGVI(4, energy_check=check),
        "CGVI(6)": dvi.CGVI(6, energy_check=check),
        "CGVI(6) chord": dvi.CGVI(6, root_finder=chord, energy_check=check),
        "CGVI(8)": dvi.CGVI(8, energy_check=check),
        "NetworkVI(tanh 10)": dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10),
                                            energy_check=check),
    }


def relative_jump(term, q0, p0, q1, p1, args):
    """`|H₁ − H₀| / (|p₀·v₀| + |L₀|)`, the quantity the solver's energy check bounds, from
    the term's public maps (an autonomous term: evaluated at t = 0)."""
    import jax.numpy as jnp

    v0 = term.velocity(0.0, q0, p0, args)
    scale = jnp.abs(jnp.sum(p0 * v0)) + jnp.abs(term(0.0, q0, v0, args))
    return jnp.abs(term.energy(0.0, q1, p1, args) - term.energy(0.0, q0, p0, args)) / scale


def measure(name, case, solver_names, wrong_level) -> list[str]:
    import diffrax
    import jax

    term, y0, args, t1, steps = case
    max_steps = int(math.ceil(t1 / min(steps))) + 2

    @jax.jit
    def local(q0, p0, h):
        sol = diffrax.diffeqsolve(
            term, diffrax.Dopri8(), 0.0, h, h / 16, (q0, p0), args=args, max_steps=10_000,
            stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
            saveat=diffrax.SaveAt(t1=True), throw=False,
        )
        return sol.ys[0][-1], sol.ys[1][-1]

    jumps = jax.jit(jax.vmap(lambda q0, p0, q1, p1: relative_jump(
        term, q0, p0, q1, p1, args)))
    local_many = jax.jit(jax.vmap(local))
    lines = []
    for solver_name, solver in solvers(False).items():
        if solver_name not in solver_names:
            continue

        @jax.jit
        def run(dt0, solver=solver):
            sol = diffrax.diffeqsolve(term, solver, 0.0, t1, dt0, y0, args=args,
                                      max_steps=max_steps, throw=False,
                                      saveat=diffrax.SaveAt(t0=True, steps=True))
            return sol.ts, sol.ys, sol.result == diffrax.RESULTS.successful

        for h in steps:
            ts, (qs, ps), ok = run(h)
            ts, qs, ps = np.asarray(ts), np.asarray(qs), np.asarray(ps)
            keep = np.all(np.isfinite(qs), 1) & np.all(np.isfinite(ps), 1) & np.isfinite(ts)
            ts, qs, ps = ts[keep], qs[keep], ps[keep]
            n = len(qs) - 1
            if n < 1:
                lines.append(f"{name:16s} {solver_name:20s} h={h:<5} its first step failed")
                print(lines[-1], flush=True)
                continue
            jump = np.asarray(jumps(qs[:-1], ps[:-1], qs[1:], ps[1:]))
            full = n
            ql, pl = local_many(qs[:full], ps[:full], np.diff(ts)[:full])
            size = 1 + np.maximum(np.max(np.abs(qs[:full]), 1), np.max(np.abs(ps[:full]), 1))
            err = np.maximum(np.max(np.abs(np.asarray(ql) - qs[1:full + 1]), 1),
                             np.max(np.abs(np.asarray(pl) - ps[1:full + 1]), 1)) / size
            jump = jump[:full]
            correct = err < wrong_level
            worst_ok = float(np.max(jump[correct])) if correct.any() else float("nan")
            best_wrong = float(np.min(jump[~correct])) if (~correct).any() else float("nan")
            lines.append(
                f"{name:16s} {solver_name:20s} h={h:<5} steps {n:4d} "
                f"{'ok    ' if bool(ok) else 'failed'} correct {int(correct.sum()):4d} "
                f"max jump {worst_ok:9.2e} | wrong {int((~correct).sum()):3d} "
                f"min jump {best_wrong:9.2e} | max local error {float(np.max(err)):9.2e}"
            )
            big = np.argsort(-jump)[:3]
            lines[-1] += " | largest jumps (jump, local error): " + ", ".join(
                f"({jump[i]:.2e}, {err[i]:.2e})" for i in big)
            print(lines[-1], flush=True)
    return lines


def cost(repeats: int) -> list[str]:
    """Per-step time of a constant-step Kepler solve (e = 0.5, h = 2π/64, 20 orbits) with and
    without the check, alternated run by run (median and best of `repeats` each), and the
    optimised HLO instructions of a 10-step solve."""
    import statistics
    import time

    import diffrax
    import jax

    import diffrax_vi as dvi
    from diffrax_vi import problems

    problem = problems.kepler(eccentricity=0.5)
    h = 2 * math.pi / 64
    n = 64 * 20
    lines = []
    for label, make in (
        ("CGVI(6)", lambda check: dvi.CGVI(6, energy_check=check)),
        ("NetworkVI(tanh 7)", lambda check: dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, 7), dvi.GaussLegendre(7), energy_check=check)),
    ):
        runs, sizes = {}, {}
        for check in (False, True):
            solver = make(check)

            def run(y0, steps, solver=solver):
                return diffrax.diffeqsolve(problem.term, solver, 0.0, steps * h, h, y0,
                                           max_steps=steps + 2,
                                           saveat=diffrax.SaveAt(t1=True)).ys

            runs[check] = jax.jit(lambda y0, run=run: run(y0, n))
            jax.block_until_ready(runs[check](problem.y0))
            hlo = jax.jit(lambda y0, run=run: run(y0, 10)).lower(problem.y0).compile().as_text()
            sizes[check] = sum(" = " in line for line in hlo.splitlines())
        from benchmarks.step_floor import kernels_per_run

        kernels = {c: kernels_per_run(runs[c], problem.y0)[0] / n for c in (False, True)}
        times = {False: [], True: []}
        for _ in range(repeats):
            for check in (False, True):
                start = time.perf_counter()
                jax.block_until_ready(runs[check](problem.y0))
                times[check].append((time.perf_counter() - start) / n * 1e6)
        off, on = (statistics.median(times[c]) for c in (False, True))
        best_off, best_on = (min(times[c]) for c in (False, True))
        lines.append(
            f"{label:18s} us/step off {off:7.3f} on {on:7.3f} (median, {on / off - 1:+.1%}); "
            f"best off {best_off:7.3f} on {best_on:7.3f} ({best_on / best_off - 1:+.1%}); "
            f"HLO of 10 steps off {sizes[False]} on {sizes[True]} "
            f"({sizes[True] / sizes[False] - 1:+.1%}); kernels/step off {kernels[False]:.1f} "
            f"on {kernels[True]:.1f}"
        )
        print(lines[-1], flush=True)
    return lines


def runs() -> list[str]:
    """The elastic pendulum to t = 20 at h = 0.2, 0.6, 0.94, constant steps and under
    `RetryFailedSteps`, with the check off and on: the result, the steps, the final error
    against Dopri8 (rtol 1e-12) and the energy at t = 20 (it starts at 0.625); for the
    default `CGVI(6)` and `NetworkVI(tanh 10)` and for the chord iteration and Newton's
    iteration, which find wrong roots there."""
    import diffrax
    import jax

    import diffrax_vi as dvi

    term, y0, args, t1 = _elastic_pendulum()
    ref = diffrax.diffeqsolve(term, diffrax.Dopri8(), 0.0, t1, 1e-3, y0, max_steps=200_000,
                              stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
                              saveat=diffrax.SaveAt(t1=True))
    ref = np.asarray(ref.ys[0][-1])
    chord = dvi.ChordIteration(ftol=0.0, predict=True, picard=False)
    basis = dvi.ShallowNetBasis(dvi.tanh, 10)
    makers = {
        "CGVI(6)": lambda c: dvi.CGVI(6, energy_check=c),
        "CGVI(6) chord": lambda c: dvi.CGVI(6, root_finder=chord, energy_check=c),
        "NetworkVI": lambda c: dvi.NetworkVI(basis, energy_check=c),
        "NetworkVI Newton": lambda c: dvi.NetworkVI(
            basis, root_finder=dvi.RoundoffNewton(confirm=False), energy_check=c),
    }
    lines = []
    for name, make in makers.items():
        for check in (False, True):
            solver = make(check)
            for label, controller in (("constant", diffrax.ConstantStepSize()),
                                      ("retry", dvi.RetryFailedSteps())):
                @jax.jit
                def solve(dt0, solver=solver, controller=controller):
                    sol = diffrax.diffeqsolve(
                        term, solver, 0.0, t1, dt0, y0, max_steps=2000, throw=False,
                        stepsize_controller=controller,
                        saveat=diffrax.SaveAt(t1=True, solver_state=True))
                    return sol.ys, sol.result, sol.stats["num_steps"], sol.solver_state.report

                for h in (0.2, 0.6, 0.94):
                    (q, p), result, steps, report = solve(h)
                    q1, p1 = q[-1], p[-1]
                    err = float(np.max(np.abs(np.asarray(q1) - ref)))
                    energy = float(term.energy(0.0, q1, p1, None))
                    lines.append(
                        f"{name:16s} check {'on ' if check else 'off'} {label:8s} h={h:<5} "
                        f"{dvi.failure_kind(result):12s} steps {int(steps):4d} "
                        f"error {err:9.2e} energy {energy:10.4g} "
                        f"last step's jump {float(report.energy_jump):9.2e}")
                    print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="*", default=None, help="problem names")
    parser.add_argument("--solvers", nargs="*", default=None)
    parser.add_argument("--wrong", type=float, default=0.05)
    parser.add_argument("--cost", type=int, default=0,
                        help="time the check instead: this many alternated repeats")
    parser.add_argument("--runs", action="store_true",
                        help="the elastic pendulum's whole runs, check off and on, instead")
    args = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.cost:
        cost(args.cost)
        return
    if args.runs:
        runs()
        return
    names = args.solvers or list(solvers(False))
    for name, case in cases().items():
        if args.only and name not in args.only:
            continue
        measure(name, case, names, args.wrong)


if __name__ == "__main__":
    main()
