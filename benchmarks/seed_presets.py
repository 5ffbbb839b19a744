"""Does NetworkVI converge from each OGA preset? Harmonic oscillator, 10 steps of h = 0.1.

For every OGA preset as `initial_guess`, with GELU and tanh networks of width 10 and a ReLU³
network of width 4 (Gauss–Legendre 8, float64), prints the solve's result, the max relative
error of q at the step ends against the exact solution, and the total nonlinear iterations.

    python -m benchmarks.seed_presets [PRESET ...]     # default: all presets
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402

PRESETS = ["OGA1d", "OGA1dNormalized", "OGA1dStable", "OGA2d", "OGASphere",
           "OGA1dNormalEquations"]
NETWORKS = {
    "gelu, width 10": (dvi.gelu, 10),
    "tanh, width 10": (dvi.tanh, 10),
    "relu3, width 4": (dvi.relu_k(3), 4),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("presets", nargs="*", default=PRESETS)
    args = parser.parse_args()
    problem = problems.harmonic_oscillator()
    ts = jnp.asarray(problem.ts)
    q_ref, _ = problem.reference(np.asarray(problem.ts))
    print("| preset | network | result | max rel. error q | iterations |")
    print("|---|---|---|---|---|")
    for name in args.presets:
        for label, (activation, width) in NETWORKS.items():
            solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, width), dvi.GaussLegendre(8),
                                   seed=dvi.SeedPolicy(initial_guess=getattr(dvi, name)()))
            run = eqx.filter_jit(lambda y0, solver=solver: diffrax.diffeqsolve(
                problem.term, solver, problem.t0, problem.t1, problem.dt, y0,
                saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False))
            sol = run(problem.y0)
            ok = sol.result == diffrax.RESULTS.successful
            error = np.max(np.abs(np.asarray(sol.ys[0]) - q_ref)) / np.max(np.abs(q_ref))
            result = "ok" if ok else diffrax.RESULTS[sol.result].split(".")[0]
            print(f"| {name} | {label} | {result} | {f'{error:.2e}' if ok else '–'} "
                  f"| {int(sol.solver_state.iterations)} |", flush=True)
            jax.clear_caches()  # many compilations in one process


if __name__ == "__main__":
    main()
