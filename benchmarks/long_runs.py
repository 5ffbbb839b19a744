"""How far one `diffeqsolve` of NetworkVI (tanh network, Gauss–Legendre nodes) gets on a
problem, and what it costs: steps done, failure report, relative energy error over 1001 saved
times (largest per tenth of the span, to tell a bounded error from a drift), wall time of the
first call (compile + run) and, with `--again`, of a second call.

Configurations: `fast` (refitted neurons, closed-form Jacobian, settle=0), `default`
(`jacobian="auto"`, otherwise the defaults), `fwd` (the defaults) and `long-run` (refits
only from steps accepted at a residual of at most 2048·eps, closed-form Jacobian: the energy
study's long-run settings). `--retry` steps with `diffrax_vi.RetryFailedSteps()` instead of
`ConstantStepSize()`: a failed step is split into smaller pieces instead of ending the run.
`--peers tsit5:1e-10 dopri8:1e-12` adds adaptive diffrax runs over the same span (as in
`energy_drift.py`). `MAXIT=200` in the environment raises `root_find_max_steps`;
`--no-restart` sets `restart_failed=False`.

    PYTHONPATH=. .venv/bin/python benchmarks/long_runs.py double_pendulum 0.05 20000 10 16 fast
    PYTHONPATH=. .venv/bin/python benchmarks/long_runs.py double_pendulum 0.05 100000 10 8 \
        default --retry --peers tsit5:1e-10 dopri8:1e-12
    PYTHONPATH=. .venv/bin/python benchmarks/long_runs.py toda_lattice 0.1 20 8 16 fast --again
"""

from __future__ import annotations

import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench.harness import retry_step_budget  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from energy_drift import _parse_peer, report_peers, span_parser  # noqa: E402

EPS = float(jnp.finfo(jnp.float64).eps)
FAST = dict(reuse_neurons=True,
            root_finder=dvi.LevenbergMarquardt(jacobian="auto", settle=0, otol=2.0**-39))
CONFIGS = {"fast": FAST, "default": dict(root_finder=dvi.LevenbergMarquardt(jacobian="auto")),
           "fwd": {},
           "long-run": dict(reuse_neurons=True, refit_residual=2048 * EPS,
                            root_finder=dvi.LevenbergMarquardt(jacobian="auto"))}


def per_tenth(ts: np.ndarray, error: np.ndarray, t0: float, t1: float) -> list[float]:
    """The largest error among the saved times in each tenth of [t0, t1] (NaN where none)."""
    edges = np.linspace(t0, t1, 11)
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        inside = error[(ts > a) & (ts <= b)]
        out.append(float(inside.max()) if inside.size else float("nan"))
    return out


def main(argv=None):
    parser = span_parser(__doc__)
    parser.add_argument("width", type=int)
    parser.add_argument("nodes", type=int)
    parser.add_argument("config", choices=sorted(CONFIGS))
    parser.add_argument("--again", action="store_true", help="time a second call")
    parser.add_argument("--no-restart", action="store_true", help="restart_failed=False")
    parser.add_argument("--retry", action="store_true",
                        help="step with RetryFailedSteps() instead of ConstantStepSize()")
    ns = parser.parse_args(argv)
    peers = [_parse_peer(parser, text) for text in ns.peers]
    problem = getattr(problems, ns.problem)(dtype=jnp.float64)
    kw = dict(CONFIGS[ns.config])
    if os.environ.get("MAXIT"):
        kw["root_find_max_steps"] = int(os.environ["MAXIT"])
    if ns.no_restart:
        kw["restart_failed"] = False
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, ns.width),
                           dvi.GaussLegendre(ns.nodes), **kw)
    h, n = ns.h, ns.steps
    t1 = problem.t0 + n * h
    ts = jnp.linspace(problem.t0, t1, 1001)
    controller = dvi.RetryFailedSteps() if ns.retry else diffrax.ConstantStepSize()
    max_steps = retry_step_budget(n) if ns.retry else n + 10

    @eqx.filter_jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, problem.t0, t1, h, y0, args=problem.args,
            stepsize_controller=controller,
            saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False,
            max_steps=max_steps)

    start = time.perf_counter()
    sol = jax.block_until_ready(run(problem.y0))
    first = time.perf_counter() - start
    state = sol.solver_state
    steps = int(state.steps)
    if ns.again:
        start = time.perf_counter()
        sol = jax.block_until_ready(run(problem.y0))
        again = time.perf_counter() - start
        print(f"first call {first:.1f} s, second {again:.2f} s = {1e3 * again / steps:.1f} "
              f"ms/step, mean iterations {int(state.iterations) / steps:.2f}")
    q, p = (np.asarray(a) for a in sol.ys)
    finite = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(p), axis=1)
    e0 = float(problem.energy(problem.t0, *problem.y0))
    energy = np.asarray(jax.vmap(lambda a, b: problem.energy(problem.t0, a, b))(
        jnp.asarray(q[finite]), jnp.asarray(p[finite])))
    error = np.abs(energy - e0) / abs(e0)
    ok = bool(sol.result == diffrax.RESULTS.successful)
    rejected = int(sol.stats["num_rejected_steps"])
    retry = f", failed trials retried in pieces {rejected}" if ns.retry else ""
    print(f"{ns.problem} h {h} steps {n} width {ns.width} nodes {ns.nodes} {ns.config}: "
          f"ok {ok}, steps done {steps}{retry}, restarts {int(state.restarts)}, first call "
          f"{first:.1f} s, max relative energy error {error.max():.2e}")
    tenths = per_tenth(np.asarray(ts)[finite], error, problem.t0, t1)
    print("  largest energy error per tenth of the span: "
          + " ".join(f"{w:.1e}" for w in tenths))
    if not ok:
        print(dvi.describe_failure(sol))
    report_peers(peers, problem, h, n, prefix="")


if __name__ == "__main__":
    main()
