"""Which per-step root finder should NetworkVI use by default? Measured on the fixtures.

For each foundation fixture (10 steps of h = 0.1, float64) and each candidate root finder, runs
`diffeqsolve` and reports the result, the max relative error of q at the step ends against the
problem's reference, the nonlinear iterations (total, median and max per step) and the run
time after compilation.

    python -m benchmarks.solver_choice          # all fixtures and root finders
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402

FIXTURES = {
    "harmonic oscillator, tanh 10, GL8": (problems.harmonic_oscillator, dvi.tanh, 10, 8),
    "harmonic oscillator, relu3 4, GL8": (problems.harmonic_oscillator, dvi.relu_k(3), 4, 8),
    "pendulum (IODE), gelu 8, GL8": (problems.pendulum, dvi.gelu, 8, 8),
    "pendulum (IODE), tanh 8, GL8": (problems.pendulum, dvi.tanh, 8, 8),
    "double pendulum, tanh 10, GL16": (
        lambda: problems.double_pendulum(t1=1.0, dt=0.1), dvi.tanh, 10, 16),
}

ROOT_FINDERS = {
    "LevenbergMarquardt(1e-3)": dvi.LevenbergMarquardt(lam=1e-3),
    "RegularisedNewton(2.4e-7)": dvi.RegularisedNewton(lam=2.4e-7),
    "RegularisedNewton(1e-5)": dvi.RegularisedNewton(lam=1e-5),
    "optx.Dogleg(1e-12)": optx.Dogleg(rtol=1e-12, atol=1e-12),
}


def run(problem, solver):
    ts = jnp.asarray(problem.ts)

    @eqx.filter_jit
    def go(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, problem.dt, y0, args=problem.args,
            saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False,
        )

    sol = go(problem.y0)
    jax.block_until_ready(sol.ys)
    start = time.perf_counter()
    sol = go(problem.y0)
    jax.block_until_ready(sol.ys)
    return sol, time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fixture", action="append", help="substring of a fixture name")
    args = parser.parse_args()
    print("| fixture | root finder | result | max rel. error q | iterations total / median / max "
          "| run ms |")
    print("|---|---|---|---|---|---|")
    for fname, (make, activation, width, nodes) in FIXTURES.items():
        if args.fixture and not any(f in fname for f in args.fixture):
            continue
        problem = make()
        for rname, root_finder in ROOT_FINDERS.items():
            solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, width),
                                   dvi.GaussLegendre(nodes), root_finder=root_finder)
            sol, elapsed = run(problem, solver)
            ok = sol.result == diffrax.RESULTS.successful
            state = sol.solver_state
            counts = np.repeat(np.arange(state.histogram.shape[0]), np.asarray(state.histogram))
            if ok:
                q_ref, _ = problem.reference(np.asarray(sol.ts))
                err = np.max(np.abs(np.asarray(sol.ys[0]) - q_ref), axis=1)
                error = f"{np.max(err / np.max(np.abs(q_ref), axis=1)):.2e}"
                result = "ok"
            else:
                error = "–"
                message = diffrax.RESULTS[sol.result].split(".")[0]
                result = f"failed at step {int(state.steps) + 1}: {message}"
            its = (f"{int(state.iterations)} / {np.median(counts):.0f} / {counts.max()}"
                   if counts.size else "–")
            print(f"| {fname} | {rname} | {result} | {error} | {its} | {elapsed * 1e3:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
