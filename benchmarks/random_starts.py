"""How often a NetworkVI solve fails over random harmonic-oscillator starts, per network width.

200 starts (seeded): amplitude uniform in (0.1, 2), phase uniform; 10 steps of h = 0.1 with
`NetworkVI(ShallowNetBasis(tanh, width), GaussLegendre(8))`, the all-parameter step
(`formulation=FreeEndpoints()`) with its default settings. Prints, per width, the failures
as `(start, steps completed, residual where the solve stopped)` and the median largest error
of q relative to the amplitude over the successful starts.

    .venv/bin/python -m benchmarks.random_starts 8 10 12 [--preset OGA1dStable]
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


def random_starts(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [(rng.uniform(0.1, 2.0), rng.uniform(0.0, 2 * np.pi)) for _ in range(count)]


def failures_for_width(width: int, starts, h: float = 0.1, steps: int = 10, preset=None):
    base = problems.harmonic_oscillator()
    ts = jnp.linspace(0.0, steps * h, steps + 1)
    seed = {} if preset is None else dict(seed=dvi.SeedPolicy(initial_guess=getattr(dvi, preset)()))
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(8),
                           formulation=dvi.FreeEndpoints(), **seed)
    run = eqx.filter_jit(lambda y0: diffrax.diffeqsolve(
        base.term, solver, 0.0, steps * h, h, y0,
        saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False))
    failed, errors = [], []
    for i, (a, phase) in enumerate(starts):
        start = problems.harmonic_oscillator(
            q0=float(a * np.cos(phase)), p0=float(-a * np.sin(phase) * np.sqrt(0.5)))
        sol = run(start.y0)
        state = sol.solver_state
        if sol.result != diffrax.RESULTS.successful:
            failed.append((i, int(state.steps), float(state.report.residual)))
            continue
        q_ref = start.reference(np.asarray(ts))[0][:, 0]
        errors.append(float(np.max(np.abs(np.asarray(sol.ys[0])[:, 0] - q_ref)) / a))
    return failed, (float(np.median(errors)) if errors else float("nan"))


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("widths", type=int, nargs="+")
    parser.add_argument("--starts", type=int, default=200)
    parser.add_argument("--preset", help="an OGA preset of diffrax_vi (default: OGA1d)")
    ns = parser.parse_args(argv)
    starts = random_starts(ns.starts)
    for width in ns.widths:
        failed, median = failures_for_width(width, starts, preset=ns.preset)
        listed = ", ".join(f"({i}, {n}, {r:.0e})" for i, n, r in failed)
        print(f"width {width}: {len(failed)} of {len(starts)} failed [{listed}]; median "
              f"max error {median:.1e}", flush=True)


if __name__ == "__main__":
    main()
