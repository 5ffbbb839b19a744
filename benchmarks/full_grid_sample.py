"""Run time of the full stability grid, measured on a random sample of its compilations.

The full grid (`diffrax_vi.bench.stability.full_grid`) has 11 664 cases per problem in 972
compilation groups (cases that differ only in dt, λ or the convergence test share one
compilation). Running all of it takes days; this script runs every case of `--groups` groups
per problem and solver, drawn at random (seeded), and extrapolates: the grid's time is
estimated per problem and solver as (number of groups) × (mean time of a sampled group), with
a bootstrap 90 % interval over the sampled groups. Each group's time is its wall time from the first
compilation to its last case, as `stability_sweep` measures it (`total_s` per case).

    .venv/bin/python -m benchmarks.full_grid_sample [--groups 2]
        [--problems harmonic_oscillator pendulum double_pendulum] [--seed 0] [--out DIR]

The Toda lattice is left out by default: one of its iterations costs about 0.3 s, so a group
whose cases run into the 1000-iteration cap takes hours.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from benchmarks.common import command_line  # noqa: E402
from diffrax_vi.bench.stability import full_grid, stability_sweep  # noqa: E402


def sample_groups(problem: str, groups: int, seed: int) -> dict[str, tuple[list, int]]:
    """Per solver (the strata: a `RegularisedNewton` group holds five λ, so five times the
    cases of a `LevenbergMarquardt` one): the cases of `groups` random compilation groups of
    `problem`, and the stratum's number of groups."""
    strata: dict[str, dict] = {}
    for case in full_grid(problems=(problem,)):
        strata.setdefault(case.solver, {}).setdefault(case.solver_key(), []).append(case)
    rng = random.Random(seed)
    out = {}
    for solver, by_key in sorted(strata.items()):
        keys = sorted(by_key, key=repr)
        chosen = rng.sample(keys, min(groups, len(keys)))
        out[solver] = ([by_key[k] for k in chosen], len(keys))
    return out


def bootstrap_means(values, draws=2000, seed=0):
    """Bootstrap draws of the mean of `values`."""
    rng = np.random.default_rng(seed)
    values = np.asarray(values)
    return rng.choice(values, (draws, len(values))).mean(axis=1)


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--groups", type=int, default=2, help="sampled groups per problem and solver"
    )
    parser.add_argument(
        "--problems", nargs="+", default=["harmonic_oscillator", "pendulum", "double_pendulum"]
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="folder for the sampled cases' CSV")
    args = parser.parse_args()
    if args.groups < 1:
        parser.error("--groups must be at least 1")
    print(f"command: {command_line('benchmarks.full_grid_sample')}")
    print(f"load average at start: {os.getloadavg()[0]:.1f}")
    grand = np.zeros(2000)
    for problem in args.problems:
        start = time.perf_counter()
        totals = np.zeros(2000)
        for solver, (groups, total_groups) in sample_groups(
            problem, args.groups, args.seed
        ).items():
            times = []
            for i, cases in enumerate(groups):
                csv_path = None
                if args.out:
                    os.makedirs(args.out, exist_ok=True)
                    csv_path = os.path.join(args.out, f"{problem}_{solver}_{i}.csv")
                rows = stability_sweep(cases, csv_path=csv_path)
                seconds = sum(r["total_s"] for r in rows)
                statuses = sorted({r["status"] for r in rows})
                key = cases[0]
                print(
                    f"{problem}: {key.dtype} R{key.nodes} S{key.width} {key.activation} "
                    f"{solver} {key.initial_guess}: {len(rows)} cases, {seconds:.1f} s, "
                    f"statuses {statuses}",
                    flush=True,
                )
                times.append(seconds)
            totals += bootstrap_means(times) * total_groups
            mean = statistics.fmean(times)
            print(f"   {solver}: {total_groups} groups, sampled group mean {mean:.1f} s")
        grand += totals
        lo, mid, hi = np.percentile(totals, [5, 50, 95]) / 3600
        print(
            f"== {problem}: sampled in {time.perf_counter() - start:.0f} s; full grid "
            f"≈ {mid:.1f} CPU-hours (90 % bootstrap interval {lo:.1f}–{hi:.1f})",
            flush=True,
        )
    lo, mid, hi = np.percentile(grand, [5, 50, 95]) / 3600
    print(f"== all sampled problems: ≈ {mid:.1f} CPU-hours (90 %: {lo:.1f}–{hi:.1f})")


if __name__ == "__main__":
    main()
