"""Kepler, e = 0.5, over 100 and 1000 orbits (issue 28): the long-run study restricted to
one problem, with the full tolerance grid of the peers.

The issue asks that the best variational configuration reach `Dopri8`'s error at no more
than half of `Dopri8`'s wall time over 100 orbits, and the same over 1000 orbits with a
position error of at most 1e-9. Report and figures go to `--out`.

    taskset -c 1 .venv/bin/python -m benchmarks.kepler_orbits \\
        [--out benchmarks/results/kepler_orbits] [--spans 100 1000]
"""

from __future__ import annotations

import argparse
import sys

import jax

jax.config.update("jax_enable_x64", True)

from diffrax_vi.bench import long_run  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/kepler_orbits")
    parser.add_argument("--spans", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--solvers", nargs="*", default=None,
                        help="variational solvers by substring (default: all)")
    args = parser.parse_args(argv)
    solvers = {k: v for k, v in long_run.VARIATIONAL.items()
               if not args.solvers or any(s in k for s in args.solvers)}
    peers = [p for p in long_run.PEERS if p.name in ("Dopri8", "Tsit5")]
    name = "kepler_e0.5"
    long_run.run_study(
        args.out, problems={name: long_run.PROBLEMS[name]}, spans={name: tuple(args.spans)},
        solvers=solvers, peers=peers, rtols=long_run.FULL_RTOLS, repeats=3, budget_s=5.0,
        max_run_s=300.0, reference_budget_s=600.0,
        command="python -m benchmarks.kepler_orbits " + " ".join(sys.argv[1:] if argv is None
                                                                else argv),
    )
    print(open(f"{args.out}/report.md").read())


if __name__ == "__main__":
    main()
