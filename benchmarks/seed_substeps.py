"""Iterations per step against the cost of the default seed's labels.

The default seed fits the network to positions from the variational midpoint rule over the
step, in `IntegratorExtrapolation(substeps=N)` sub-steps (N = 10 by default, the reference's).
More sub-steps give more accurate labels and, with tanh networks, a seed nearer the root and
fewer Levenberg–Marquardt iterations, but the labels and the fit on N + 1 points cost more
(and with GELU networks the runs fail: `--activation gelu`). This script measures that trade
for each N under three stopping rules: the defaults, no waiting iterations at the residual
floor (`settle=0`), and the early stop of the fast configuration (`settle=0, otol=2**-39`),
with the closed-form Jacobian in all.

Per row: success, median and mean iterations per step, error of q at the end relative to the
amplitude, and ms per step (median of `--repeats` runs after compiling; the configurations'
runs are interleaved, so a load on the machine falls on all of them alike).

    .venv/bin/python -m benchmarks.seed_substeps [--substeps 10 20 40 100]
        [--problems double_pendulum] [--rules "early stop"] [--steps N] [--repeats R]
        [--activation gelu]
"""

from __future__ import annotations

import argparse
import statistics

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import iteration_summary, timed  # noqa: E402

H = 0.1
# name: (problem, Gauss-Legendre nodes, steps); the first two as in benchmarks/speed.py
FIXTURES = {
    "harmonic_oscillator": ("harmonic_oscillator", 8, 200),
    "double_pendulum": ("double_pendulum", 16, 20),
    "henon_heiles": ("henon_heiles", 8, 200),
    "kepler": ("kepler", 8, 200),
}
RULES = {
    "defaults": dict(jacobian="auto"),
    "settle 0": dict(jacobian="auto", settle=0),
    "early stop": dict(jacobian="auto", settle=0, otol=2.0**-39),
}


def compiled_run(problem, nodes: int, steps: int, rule: str, substeps: int, activation):
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(activation, 10), dvi.GaussLegendre(nodes),
        seed=dvi.SeedPolicy(initial_trajectory=dvi.IntegratorExtrapolation(substeps=substeps)),
        root_finder=dvi.LevenbergMarquardt(**RULES[rule]))

    @eqx.filter_jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, H, y0, args=problem.args,
            saveat=diffrax.SaveAt(t1=True, solver_state=True), max_steps=steps + 1,
            throw=False)

    return run


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--substeps", type=int, nargs="+", default=[10, 20, 40, 100])
    parser.add_argument("--problems", nargs="+", choices=sorted(FIXTURES),
                        default=["double_pendulum", "harmonic_oscillator"])
    parser.add_argument("--rules", nargs="+", choices=sorted(RULES),
                        default=["defaults", "early stop"])
    parser.add_argument("--steps", type=int, default=None,
                        help="steps per fixture (default: 200 oscillator, 20 double pendulum)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--activation", choices=["tanh", "gelu"], default="tanh")
    ns = parser.parse_args(argv)
    print(f"| fixture ({ns.activation} width 10, h = 0.1) | stopping rule | sub-steps | ok "
          "| iters median | iters mean | rel. error q(t end) | ms/step |")
    print("|---|---|---|---|---|---|---|---|")
    for name in ns.problems:
        kind, nodes, steps = FIXTURES[name]
        steps = ns.steps or steps
        problem = getattr(problems, kind)(dtype=jnp.float64).with_span(n_steps=steps, dt=H)
        amplitude = float(np.max(np.abs(problem.reference(problem.ts)[0])))
        rows = {}
        for rule in ns.rules:
            for n in ns.substeps:
                run = compiled_run(problem, nodes, steps, rule, n,
                                   getattr(dvi, ns.activation))
                sol, _ = timed(run, problem.y0)
                rows[rule, n] = (run, sol, [])
        for _ in range(ns.repeats):
            for run, _, times in rows.values():
                times.append(timed(run, problem.y0)[1])
        for (rule, n), (_, sol, times) in rows.items():
            ok = bool(sol.result == diffrax.RESULTS.successful)
            t_end = float(sol.ts[-1])
            q_ref = problem.reference(np.array([t_end]))[0][0]
            error = float(np.max(np.abs(np.asarray(sol.ys[0][-1]) - q_ref))) / amplitude
            its = iteration_summary(sol.solver_state)
            wall = statistics.median(times) if times else float("nan")
            ms = 1e3 * wall / max(its["steps"], 1)
            print(f"| {name}, GL{nodes}, {steps} steps | {rule} | {n} | {ok} | "
                  f"{its['it_median']} | {its['it_mean']:.2f} | {error:.2e} | {ms:.2f} |",
                  flush=True)


if __name__ == "__main__":
    main()
