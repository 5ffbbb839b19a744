"""The variable-projection step against the all-parameter step and CGVI, side by side.

Per fixture and formulation: the diffrax result, the largest error of q over the saved times
relative to the amplitude, median and largest nonlinear iterations per step, the last step's
residual, and (for the timed fixture) milliseconds per run and per step after compiling
(median of `--repeats`). The vmap row solves four oscillators (amplitudes 0.3, 0.5, 0.7, 0.9)
under `jax.vmap` and as a loop of single solves and prints their largest difference.

    .venv/bin/python -m benchmarks.projection [--repeats 3] [--quick]
        [--sections fixtures vmap timing energy] [--energy-steps 2000 100000]

The energy section runs the oscillator at h = 0.5 and prints the largest relative energy
error over the run, and over its first and second halves (a linear drift doubles it).
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.activations import activation_name  # noqa: E402

SECTIONS = ("fixtures", "vmap", "timing", "energy")
FORMULATIONS = {
    "projection (uniform layer)": dvi.VariableProjection,
    "projection (first seed's layer)": lambda: dvi.VariableProjection(
        hidden=dvi.FirstSeedLayer()
    ),
    "projection (each seed's layer)": lambda: dvi.VariableProjection(hidden=dvi.SeedLayer()),
    "all-parameter": dvi.FreeEndpoints,
}


def network(activation, width, nodes, formulation):
    return dvi.NetworkVI(
        dvi.ShallowNetBasis(activation, width), dvi.GaussLegendre(nodes), formulation=formulation
    )


def compiled(problem, solver):
    ts = jnp.asarray(problem.ts)
    saveat = diffrax.SaveAt(ts=ts, solver_state=True)
    return eqx.filter_jit(
        lambda y0, throw=True: diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, problem.dt, y0, args=problem.args,
            saveat=saveat, max_steps=100_000, throw=throw,
        )
    )


def max_error(problem, sol) -> float:
    q_ref, _ = problem.reference(np.asarray(sol.ts))
    q = np.asarray(sol.ys[0])
    return float(np.max(np.max(np.abs(q - q_ref), axis=1) / np.max(np.abs(q_ref), axis=1)))


def iterations(sol) -> tuple[int, int]:
    hist = np.asarray(sol.solver_state.histogram)
    cum = np.cumsum(hist)
    return int(np.searchsorted(cum, cum[-1] / 2)), int(sol.solver_state.max_iterations)


def fixtures(quick: bool):
    rows = [
        ("oscillator h=0.1", problems.harmonic_oscillator(), dvi.tanh, 10, 8),
        ("oscillator h=0.1", problems.harmonic_oscillator(), dvi.tanh, 12, 10),
        ("double pendulum h=0.1", problems.double_pendulum(t1=1.0, dt=0.1), dvi.tanh, 10, 16),
        ("pendulum (IODE) h=0.1", problems.pendulum(), dvi.gelu, 8, 8),
    ]
    return rows[:1] if quick else rows


def run(args) -> None:
    if "fixtures" in args.sections:
        fixture_table(args)
    if "vmap" in args.sections:
        vmap_against_loop()
    if "timing" in args.sections:
        timing(args)
    if "energy" in args.sections:
        energy(args)


def fixture_table(args) -> None:
    print("| fixture | network | formulation | result | max error | iterations (median/max) "
          "| residual |")
    print("|---|---|---|---|---|---|---|")
    for label, problem, activation, width, nodes in fixtures(args.quick):
        for name, form in FORMULATIONS.items():
            solve = compiled(problem, network(activation, width, nodes, form()))
            sol = solve(problem.y0, throw=False)
            med, most = iterations(sol)
            ok = sol.result == diffrax.RESULTS.successful
            error = f"{max_error(problem, sol):.2e}" if ok else "-"
            print(f"| {label} | {activation_name(activation)} {width}, GL{nodes} | {name} | "
                  f"{'ok' if ok else 'failed'} | {error} | {med}/{most} | "
                  f"{float(sol.solver_state.report.residual):.1e} |")



def vmap_against_loop() -> None:
    print("\nvmap of four oscillators against the loop of single solves (tanh 10, GL8):")
    problem = problems.harmonic_oscillator()
    amplitudes = [0.3, 0.5, 0.7, 0.9]
    for name, form in FORMULATIONS.items():
        solve = compiled(problem, network(dvi.tanh, 10, 8, form()))
        loop = np.stack([np.asarray(solve((jnp.array([a]), jnp.zeros(1))).ys[0])
                         for a in amplitudes])
        batched = jax.vmap(lambda a, f=solve: f((a[None], jnp.zeros(1))).ys[0])
        vm = np.asarray(batched(jnp.array(amplitudes)))
        print(f"- {name}: max |vmap - loop| = {np.abs(vm - loop).max():.1e}")



def timing(args) -> None:
    steps = 20 if args.quick else 200
    timed_fixtures = [
        ("oscillator h = 0.5", problems.harmonic_oscillator().with_span(n_steps=steps, dt=0.5),
         8),
        ("double pendulum h = 0.1",
         problems.double_pendulum().with_span(n_steps=steps, dt=0.1), 16),
    ]
    for label, problem, nodes in timed_fixtures[: 1 if args.quick else 2]:
        print(f"\n{label}, {steps} steps (tanh 10, GL{nodes}; CGVI(7) with GL8), "
              f"median of {args.repeats} runs after compiling:")
        print("| solver | result | max error | iterations (median) | compile + first run (s) "
              "| ms per run | us per step | time / CGVI(7) |")
        print("|---|---|---|---|---|---|---|---|")
        solvers = {
            name: network(dvi.tanh, 10, nodes, form()) for name, form in FORMULATIONS.items()
        }
        solvers["CGVI(7)"] = dvi.CGVI(7, dvi.GaussLegendre(8))
        results = {}
        for name, solver in solvers.items():
            start = time.perf_counter()
            solve = compiled(problem, solver)
            sol = jax.block_until_ready(solve(problem.y0, throw=False))
            first = time.perf_counter() - start
            results[name] = (solve, sol, first, [])
        for _ in range(args.repeats):  # interleaved, so that a load falls on all alike
            for solve, _, _, times in results.values():
                start = time.perf_counter()
                jax.block_until_ready(solve(problem.y0, throw=False).ys)
                times.append(time.perf_counter() - start)
        base = statistics.median(results["CGVI(7)"][3])
        for name, (_, sol, first, times) in results.items():
            med = statistics.median(times)
            ok = sol.result == diffrax.RESULTS.successful
            error = f"{max_error(problem, sol):.2e}" if ok else "-"
            print(f"| {name} | {'ok' if ok else 'failed'} | {error} | {iterations(sol)[0]} | "
                  f"{first:.1f} | {med * 1e3:.1f} | {med / steps * 1e6:.0f} | "
                  f"{med / base:.1f} |")


def energy(args) -> None:
    print("\noscillator h = 0.5: largest relative energy error over the run (at up to 201 step "
          "ends; tanh 10, GL8)")
    print("| steps | solver | result | max energy error | first half | second half |")
    print("|---|---|---|---|---|---|")
    for steps in args.energy_steps:
        problem = problems.harmonic_oscillator().with_span(n_steps=steps, dt=0.5)
        solvers = {
            "projection (uniform layer)": network(dvi.tanh, 10, 8, dvi.VariableProjection()),
            "all-parameter": network(dvi.tanh, 10, 8, dvi.FreeEndpoints()),
            "CGVI(7)": dvi.CGVI(7, dvi.GaussLegendre(8)),
        }
        # step ends only (inside a step the dense output is less accurate than the step)
        ends = np.unique(np.round(np.linspace(0, steps, min(steps, 200) + 1)))
        ts = jnp.asarray(problem.t0 + 0.5 * ends)
        for name, solver in solvers.items():
            if name == "all-parameter" and steps > args.all_parameter_steps:
                continue
            sol = diffrax.diffeqsolve(
                problem.term, solver, problem.t0, problem.t1, problem.dt, problem.y0,
                args=problem.args, saveat=diffrax.SaveAt(ts=ts), max_steps=steps + 10,
                throw=False,
            )
            e = np.asarray(jax.vmap(lambda q, p: problem.energy(0.0, q, p))(*sol.ys))
            rel = np.abs(e - e[0]) / abs(e[0])
            ok = "ok" if sol.result == diffrax.RESULTS.successful else "failed"
            half = len(rel) // 2 + 1
            print(f"| {steps} | {name} | {ok} | {np.nanmax(rel):.2e} | "
                  f"{np.nanmax(rel[:half]):.2e} | {np.nanmax(rel[half:]):.2e} |")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one fixture, 20 timed steps")
    parser.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    parser.add_argument("--energy-steps", nargs="+", type=int, default=[2000])
    parser.add_argument("--all-parameter-steps", type=int, default=2000,
                        help="longest energy run of the all-parameter solve (it is slow)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    run(args)


if __name__ == "__main__":
    main()
