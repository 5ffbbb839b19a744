"""Where the first call of a NetworkVI `diffeqsolve` spends its time: tracing and lowering
to XLA, and XLA's compilation, with the size of the lowered program (characters of its
StableHLO text), for one fixture and configuration. Medians over `--repeats` fresh traces.

Configurations as in `benchmarks/speed.py` (`default`, `jacrev`, `auto`, `fast`);
`--no-restart` sets `restart_failed=False` (the program should not change: the fresh seed fit
is the root finder's fallback either way).

    PYTHONPATH=. .venv/bin/python benchmarks/compile_phases.py double_pendulum fast
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from speed import CONFIGS  # noqa: E402  (the configurations of benchmarks/speed.py)

NODES = {"harmonic_oscillator": 8, "double_pendulum": 16}


def phases(problem_name: str, config: str, restart: bool = True, steps: int = 20, h=0.1):
    """(trace + lower seconds, compile seconds, StableHLO characters) of one solve."""
    problem = getattr(problems, problem_name)(dtype=jnp.float64).with_span(n_steps=steps, dt=h)
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 10),
        dvi.GaussLegendre(NODES.get(problem_name, 8)),
        restart_failed=restart,
        **CONFIGS[config],
    )

    def run(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, h, y0, args=problem.args,
            saveat=diffrax.SaveAt(t1=True), max_steps=steps + 1, throw=False,
        )  # fmt: skip

    start = time.perf_counter()
    lowered = jax.jit(run).lower(problem.y0)
    traced = time.perf_counter() - start
    size = len(lowered.as_text())
    start = time.perf_counter()
    lowered.compile()
    return traced, time.perf_counter() - start, size


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("problem", choices=sorted(NODES))
    parser.add_argument("config", choices=sorted(CONFIGS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-restart", action="store_true")
    ns = parser.parse_args(argv)
    rows = []
    for _ in range(ns.repeats):
        jax.clear_caches()
        rows.append(phases(ns.problem, ns.config, restart=not ns.no_restart))
    trace, compile_s, size = (statistics.median(r[i] for r in rows) for i in range(3))
    print(f"{ns.problem} {ns.config} restart_failed={not ns.no_restart}: trace+lower "
          f"{trace:.2f} s, XLA compile {compile_s:.2f} s, first call without the run "
          f"{trace + compile_s:.2f} s, StableHLO {size / 1e6:.2f} M characters "
          f"(medians of {ns.repeats})")


if __name__ == "__main__":
    main()
