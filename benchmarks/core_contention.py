"""How much two busy cores slow each other: the ceiling of any two-process speed-up here.

One compiled solve (the default `NetworkVI` on the double pendulum, GL16, 2000 steps of 0.05)
is timed over a window in one process pinned to one core, alone; then two such processes run
at once, one pinned to each core. The ratio of the two medians is what sharing the machine
costs a process; `2 × alone / together` is the throughput of two processes against one, the
most that two workers of a sweep can gain over one process on this machine (before start-up,
imbalance and compilation).

    .venv/bin/python -m benchmarks.core_contention [--window 30]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

from .common import module_command

CHILD = "--child"


def child(window: float) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax

    import diffrax_vi as dvi
    from diffrax_vi import problems

    problem = problems.double_pendulum()
    h, n = 0.05, 2000
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(16))

    @jax.jit
    def run(y):
        sol = diffrax.diffeqsolve(problem.term, solver, 0.0, n * h, h, y, max_steps=n,
                                  saveat=diffrax.SaveAt(t1=True), throw=False)
        return sol.ys[0]

    jax.block_until_ready(run(problem.y0))
    print("READY", flush=True)
    sys.stdin.readline()  # start the window together with the other process
    times = []
    end = time.time() + window
    while time.time() < end:
        start = time.perf_counter()
        jax.block_until_ready(run(problem.y0))
        times.append(time.perf_counter() - start)
    print(f"MEDIAN {statistics.median(times)} {len(times)}", flush=True)


def timed(cores: list[int], window: float) -> list[tuple[float, int]]:
    """Medians of the solve in one process per core of `cores`, their windows started at
    once after every process has compiled."""
    procs = [
        subprocess.Popen(["taskset", "-c", str(c), *module_command(
            "benchmarks.core_contention", CHILD, "--window", str(window))],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        for c in cores
    ]
    for p in procs:
        assert p.stdout.readline().strip() == "READY"
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    out = []
    for p in procs:
        line = p.stdout.readline().split()
        p.wait()
        out.append((float(line[1]), int(line[2])))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--window", type=float, default=30.0, help="seconds timed per run")
    parser.add_argument(CHILD, action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.window <= 0:
        parser.error(f"--window must be positive, got {args.window}")
    if args.child:
        child(args.window)
        return
    cores = sorted(os.sched_getaffinity(0))[:2]
    if len(cores) < 2:
        raise SystemExit("needs two CPUs")
    print("command: python -m benchmarks.core_contention --window", args.window)
    print("default NetworkVI (tanh 10, GL16), double pendulum, 2000 steps of 0.05, float64\n")
    alone = [timed([c], args.window)[0] for c in cores]
    together = timed(cores, args.window)
    print("| run | core | median ms per solve | solves |")
    print("|---|---|---|---|")
    for label, rows in (("alone", alone), ("both cores busy", together)):
        for core, (median, count) in zip(cores, rows, strict=True):
            print(f"| {label} | {core} | {median * 1e3:.1f} | {count} |")
    a = statistics.mean(m for m, _ in alone)
    b = statistics.mean(m for m, _ in together)
    print(f"\na solve takes {b / a:.2f}x as long with both cores busy; two processes give "
          f"{2 * a / b:.2f}x the throughput of one")


if __name__ == "__main__":
    main()
