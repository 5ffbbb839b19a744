"""Where the first call of a NetworkVI `diffeqsolve` spends its time: tracing and lowering
to XLA, and XLA's compilation, with the size of the lowered program (characters of its
StableHLO text), for one fixture and configuration. Medians over `--repeats` fresh traces.

Configurations as in `benchmarks/speed.py` (`default`, `jacrev`, `auto`, `fast`);
`--no-restart` sets `restart_failed=False` (the program should not change: the fresh seed fit
is the root finder's fallback either way).

`--fresh` measures what a user's first call costs: the first call (tracing, compiling and
one run of the solve) in `--repeats` fresh Python processes, without a cache. The medians of
the default mode come from later traces in one process, after `jax.clear_caches()`, which
cost less: JAX's and XLA's first compilation in a process also pays for their own start.

`--cache` measures JAX's persistent compilation cache instead: the same first call (tracing,
compiling and one run of the solve) in `--repeats` fresh Python processes sharing one new
cache directory, so the first compiles and writes the cache and the others read it.

    .venv/bin/python -m benchmarks.compile_phases double_pendulum fast
    .venv/bin/python -m benchmarks.compile_phases double_pendulum fast --cache
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import subprocess
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.common import ROOT, module_command  # noqa: E402
from benchmarks.speed import CONFIGS  # noqa: E402  (the configurations of benchmarks.speed)
from diffrax_vi import problems  # noqa: E402

NODES = {"harmonic_oscillator": 8, "double_pendulum": 16}


def fixture_solve(problem_name: str, config: str, restart: bool = True, steps: int = 20, h=0.1):
    """The fixture's solve as a function of `y0` (not jitted), and the problem."""
    problem = getattr(problems, problem_name)(dtype=jnp.float64).with_span(n_steps=steps, dt=h)
    options = dict(CONFIGS[config])
    seed = dataclasses.replace(options.pop("seed", dvi.SeedPolicy()), restart_failed=restart)
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 10),
        dvi.GaussLegendre(NODES.get(problem_name, 8)),
        seed=seed,
        **options,
    )

    def run(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, h, y0, args=problem.args,
            saveat=diffrax.SaveAt(t1=True), max_steps=steps + 1, throw=False,
        )  # fmt: skip

    return run, problem


def phases(problem_name: str, config: str, restart: bool = True, steps: int = 20, h=0.1):
    """(trace + lower seconds, compile seconds, StableHLO characters) of one solve."""
    run, problem = fixture_solve(problem_name, config, restart, steps, h)
    start = time.perf_counter()
    lowered = jax.jit(run).lower(problem.y0)
    traced = time.perf_counter() - start
    size = len(lowered.as_text())
    start = time.perf_counter()
    lowered.compile()
    return traced, time.perf_counter() - start, size


def first_call(problem_name: str, config: str, steps: int = 20, h=0.1) -> float:
    """Seconds of the first call of one solve (trace, compile or cache read, one run)."""
    run, problem = fixture_solve(problem_name, config, steps=steps, h=h)
    start = time.perf_counter()
    jax.block_until_ready(jax.jit(run)(problem.y0))
    return time.perf_counter() - start


def cached_first_calls(problem_name: str, config: str, processes: int = 3, steps: int = 20,
                       cache: bool = True):
    """First-call seconds in `processes` fresh processes sharing a new persistent cache (or,
    without `cache`, each without one)."""
    out = []
    with tempfile.TemporaryDirectory() as directory:
        for _ in range(processes):
            child = ("--child-cache", directory) if cache else ("--child-fresh",)
            line = subprocess.run(
                module_command("benchmarks.compile_phases", problem_name, config, *child,
                               "--steps", str(steps)),
                check=True, capture_output=True, text=True, cwd=ROOT,
                env=dict(os.environ, EQX_ON_ERROR="nan"),  # no host callback in the program
            ).stdout.strip().splitlines()[-1]
            out.append(float(line))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("problem", choices=sorted(NODES))
    parser.add_argument("config", choices=sorted(CONFIGS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-restart", action="store_true")
    parser.add_argument("--cache", action="store_true",
                        help="first calls in fresh processes sharing a persistent cache")
    parser.add_argument("--fresh", action="store_true",
                        help="first calls in fresh processes, without a cache")
    parser.add_argument("--steps", type=int, default=20, help=argparse.SUPPRESS)
    parser.add_argument("--child-cache", help=argparse.SUPPRESS)
    parser.add_argument("--child-fresh", action="store_true", help=argparse.SUPPRESS)
    ns = parser.parse_args(argv)
    if ns.child_cache:
        jax.config.update("jax_compilation_cache_dir", ns.child_cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if ns.child_cache or ns.child_fresh:
        print(first_call(ns.problem, ns.config, ns.steps))
        return
    if ns.fresh:
        seconds = cached_first_calls(ns.problem, ns.config, ns.repeats, ns.steps, cache=False)
        print(f"{ns.problem} {ns.config}: first call in fresh processes without a cache: "
              + ", ".join(f"{s:.2f} s" for s in seconds)
              + f" (median {statistics.median(seconds):.2f} s)")
        return
    if ns.cache:
        seconds = cached_first_calls(ns.problem, ns.config, max(ns.repeats, 2), ns.steps)
        print(f"{ns.problem} {ns.config}: first call in fresh processes sharing a persistent "
              f"compilation cache: " + ", ".join(f"{s:.2f} s" for s in seconds)
              + " (the first one compiles and writes the cache)")
        return
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
