"""How far one `diffeqsolve` of NetworkVI (tanh network, Gauss–Legendre nodes) gets on a
problem, and what it costs: steps done, failure report, relative energy error over 101 saved
times, wall time of the first call (compile + run) and, with `--again`, of a second call.

Configurations: `fast` (refitted neurons, closed-form Jacobian, settle=0), `default`
(`jacobian="auto"`, otherwise the defaults) and `fwd` (the defaults). `MAXIT=200` in the
environment raises `root_find_max_steps`; `--no-restart` sets `restart_failed=False`.

    PYTHONPATH=. .venv/bin/python benchmarks/long_runs.py double_pendulum 0.05 20000 10 16 fast
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

FAST = dict(reuse_neurons=True,
            root_finder=dvi.LevenbergMarquardt(jacobian="auto", settle=0, otol=2.0**-39))
CONFIGS = {"fast": FAST, "default": dict(root_finder=dvi.LevenbergMarquardt(jacobian="auto")),
           "fwd": {}}


def main(argv):
    name, h, n, width, nodes, config = argv[:6]
    h, n, width, nodes = float(h), int(n), int(width), int(nodes)
    problem = getattr(problems, name)(dtype=jnp.float64)
    kw = dict(CONFIGS[config])
    if os.environ.get("MAXIT"):
        kw["root_find_max_steps"] = int(os.environ["MAXIT"])
    if "--no-restart" in argv:
        kw["restart_failed"] = False
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(nodes), **kw)
    t1 = problem.t0 + n * h
    ts = jnp.linspace(problem.t0, t1, 101)

    @eqx.filter_jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, problem.t0, t1, h, y0, args=problem.args,
            saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False, max_steps=n + 10)

    start = time.perf_counter()
    sol = jax.block_until_ready(run(problem.y0))
    first = time.perf_counter() - start
    state = sol.solver_state
    steps = int(state.steps)
    if "--again" in argv:
        start = time.perf_counter()
        sol = jax.block_until_ready(run(problem.y0))
        again = time.perf_counter() - start
        print(f"first call {first:.1f} s, second {again:.2f} s = {1e3 * again / steps:.1f} "
              f"ms/step, mean iterations {int(state.iterations) / steps:.2f}")
    q, p = (np.asarray(a) for a in sol.ys)
    e0 = float(problem.energy(problem.t0, *problem.y0))
    energies = [float(problem.energy(problem.t0, jnp.asarray(a), jnp.asarray(b)))
                for a, b in zip(q, p, strict=True) if np.all(np.isfinite(a))]
    ok = bool(sol.result == diffrax.RESULTS.successful)
    print(f"{name} h {h} steps {n} width {width} {config}: ok {ok}, steps done {steps}, "
          f"restarts {int(state.restarts)}, first call {first:.1f} s, max relative energy "
          f"error {np.max(np.abs(np.array(energies) - e0)) / abs(e0):.2e}")
    if not ok:
        print(dvi.describe_failure(sol))


if __name__ == "__main__":
    main(sys.argv[1:])
