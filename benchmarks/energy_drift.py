"""Where NetworkVI's long-run energy error comes from: the residual each step is accepted at.

A variational integrator whose steps solve their equations exactly keeps the energy error
bounded (`CGVI(7)` below). A network step is accepted at a residual floor that its
rank-deficient, sometimes ill-conditioned Jacobian leaves, so the map applied is not exactly
the variational one, and every step adds an energy error of about the size of that residual.
This script runs `NetworkVI.step` in one compiled `lax.scan` per configuration and reports,
per configuration:

- the least-squares slope of the relative energy error against the step number (a drift, as
  against a bounded oscillation, shows as a slope that stays when the run gets longer);
- the largest relative energy error in each tenth of the run;
- the per-step energy change `|ΔE|/|E₀|` and the accepted residual `max|F|` (median, 99th
  percentile, largest), and the correlation of their logarithms.

Configurations (`--configs`): `default` (the solver's defaults: the projected step),
`all` (the all-parameter formulation, OGA1d seed on every step), `oga2d` (the OGA2d preset
as seed), `fast` (`benchmarks/speed.py`'s fast configuration: refitted neurons, solve ended at
the first settled exact iteration), its two halves on their own: `settle0` (OGA seed, early
stop) and `refit` (refitted neurons, the default stop), `refit_limited` (the same, refitting
only from roots accepted at a residual of at most `2048·eps`, `refit_residual`), the default
seed with a shorter stopping rule (`settle1`, `settle2`: that many iterations without the
residual halving before settled outputs end a solve, against 3 by default; `settle0_otol`: none,
with the default output tolerance `64·eps`, where `settle0` uses `eps^(3/4)`), and
`cgvi` (`CGVI(7)`, the polynomial baseline). A tanh network of width `--width` (default 10)
on `--nodes` Gauss–Legendre nodes (default 8), float64. `--peers tsit5:1e-10 dopri8:1e-12`
adds adaptive diffrax runs over the same span (PID controller, atol = rtol/100), their energy
sampled at 1000 evenly spaced times.

    .venv/bin/python -m benchmarks.energy_drift harmonic_oscillator 0.25 4000
    .venv/bin/python -m benchmarks.energy_drift henon_heiles 0.1 4000 \
        --configs default oga2d
"""

from __future__ import annotations

import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.common import parse_peer, report_peers, span_parser  # noqa: E402
from benchmarks.speed import CONFIGS as SPEED_CONFIGS  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import timed  # noqa: E402

EPS = float(jnp.finfo(jnp.float64).eps)


def solver_for(config: str, width: int = 10, nodes: int = 8):
    """The solver of a configuration name (see the module docstring)."""
    if config == "cgvi":
        return dvi.CGVI(7, dvi.GaussLegendre(8))
    early_stop = dvi.LevenbergMarquardt(jacobian="auto", settle=0, otol=2.0**-39)
    options = {"default": {}, "all": dict(formulation=dvi.FreeEndpoints()),
               "oga2d": dict(seed=dvi.SeedPolicy(initial_guess=dvi.OGA2d())),
               "fast": SPEED_CONFIGS["fast"],
               "settle0": dict(root_finder=early_stop),
               # the default seed and output tolerance, fewer iterations at the floor
               "settle0_otol": dict(root_finder=dvi.LevenbergMarquardt(settle=0)),
               "settle1": dict(root_finder=dvi.LevenbergMarquardt(settle=1)),
               "settle2": dict(root_finder=dvi.LevenbergMarquardt(settle=2)),
               "refit": dict(seed=dvi.SeedPolicy(reuse_neurons=True),
                             root_finder=dvi.LevenbergMarquardt(jacobian="auto")),
               "refit_limited": dict(
                   seed=dvi.SeedPolicy(reuse_neurons=True, refit_residual=2048 * EPS),
                   root_finder=dvi.LevenbergMarquardt(jacobian="auto")),
               }[config]
    return dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(nodes),
                         **options)


def run_steps(solver, problem, h: float, steps: int, repeats: int = 0):
    """`steps` fixed steps from the problem's start in one compiled scan. Returns the states
    `(q, p)` after each step, whether each step succeeded, each step's final residual
    (zeros for solvers without a `report`), the number of steps seeded by a refit
    (`NetworkVIState.refits`; 0 for other solvers), the median wall time of `repeats`
    further runs of the compiled scan (NaN for none), and the median nonlinear iterations
    per step before the first failed one (from each step's `report`; NaN for solvers
    without one)."""
    term, args = problem.term, problem.args

    @eqx.filter_jit
    def scan(y0):
        state = solver.init(term, problem.t0, problem.t0 + h, y0, args)

        def body(carry, k):
            y, state = carry
            t0 = problem.t0 + k * h
            y1, _, _, state1, result = solver.step(term, t0, t0 + h, y, args, state, False)
            report = getattr(state1, "report", None)
            residual = jnp.zeros(()) if report is None else report.residual
            iterations = jnp.zeros((), jnp.int32) if report is None else report.iterations
            ok = result == diffrax.RESULTS.successful
            return (y1, state1), (y1, ok, residual, iterations)

        (_, state), outs = jax.lax.scan(body, (y0, state), jnp.arange(steps))
        return outs, getattr(state, "refits", jnp.zeros((), jnp.int32))

    ((q, p), ok, residual, iterations), refits = scan(problem.y0)
    ok, iterations = np.asarray(ok), np.asarray(iterations)
    # over the steps before the first failure (the steps after it start from NaN)
    done = int(np.argmin(ok)) if not ok.all() else ok.size
    median_iterations = (float(np.median(iterations[:done]))
                         if done and getattr(solver, "root_finder", None) is not None
                         else float("nan"))
    times = [timed(scan, problem.y0)[1] for _ in range(repeats)]
    steady = statistics.median(times) if times else float("nan")
    return (np.asarray(q), np.asarray(p), ok, np.asarray(residual), int(refits),
            steady, median_iterations)


def drift_summary(problem, q, p, residual) -> dict:
    """Energy drift and accepted-residual statistics of one run (see the module docstring)."""
    e0 = float(problem.energy(problem.t0, *problem.y0))
    energy = np.asarray(jax.vmap(lambda a, b: problem.energy(problem.t0, a, b))(q, p))
    rel = (energy - e0) / abs(e0)
    steps = rel.size
    change = np.abs(np.diff(np.concatenate([[0.0], rel])))
    tenth = max(steps // 10, 1)
    windows = [float(np.abs(rel[i:i + tenth]).max()) for i in range(0, steps, tenth)][:10]
    positive = (change > 0) & (residual > 0)
    corr = (float(np.corrcoef(np.log(change[positive]), np.log(residual[positive]))[0, 1])
            if positive.sum() > 2 else float("nan"))
    return dict(
        slope=float(np.polyfit(np.arange(1, steps + 1), rel, 1)[0]) if steps > 1 else 0.0,
        windows=windows,
        change=(float(np.median(change)), float(np.percentile(change, 99)), float(change.max())),
        residual=(float(np.median(residual)), float(np.percentile(residual, 99)),
                  float(residual.max())),
        corr=corr,
    )


def main(argv=None):
    parser = span_parser(__doc__)
    parser.add_argument("--configs", nargs="+", default=["default", "oga2d", "fast", "cgvi"])
    parser.add_argument("--repeats", type=int, default=3,
                        help="timed runs after the first (compiling) one; median quoted")
    parser.add_argument("--width", type=int, default=10, help="network width (default 10)")
    parser.add_argument("--nodes", type=int, default=8,
                        help="Gauss-Legendre nodes (default 8)")
    ns = parser.parse_args(argv)
    peers = [parse_peer(parser, text) for text in ns.peers]
    problem = getattr(problems, ns.problem)(dtype=jnp.float64)
    print(f"{ns.problem}, {ns.steps} steps of h = {ns.h}, float64, tanh width {ns.width}, "
          f"Gauss-Legendre {ns.nodes}; relative energy error")
    for config in ns.configs:
        start = time.perf_counter()
        q, p, ok, residual, refits, steady, iterations = run_steps(
            solver_for(config, ns.width, ns.nodes), problem, ns.h, ns.steps, ns.repeats)
        first = time.perf_counter() - start - (steady * ns.repeats if ns.repeats else 0.0)
        done = int(np.argmin(ok)) if not ok.all() else ns.steps
        s = drift_summary(problem, q[:done], p[:done], residual[:done])
        status = "all steps ok" if done == ns.steps else f"step {done + 1} failed"
        print(f"\n{config}: {status}, {refits} steps seeded by a refit; first run about "
              f"{first:.0f} s, then {1e3 * steady / ns.steps:.2f} ms per step "
              f"(median of {ns.repeats}); median {iterations:.0f} iterations per step")
        print(f"  slope {s['slope']:.2e} per step; largest per tenth: "
              + " ".join(f"{w:.1e}" for w in s["windows"]))
        median, p99, largest = s["change"]
        print(f"  per-step |ΔE| median {median:.1e}, p99 {p99:.1e}, max {largest:.1e}")
        median, p99, largest = s["residual"]
        print(f"  accepted residual median {median:.1e}, p99 {p99:.1e}, max {largest:.1e}; "
              f"log correlation {s['corr']:.2f}")
    report_peers(peers, problem, ns.h, ns.steps)


if __name__ == "__main__":
    main()
