"""Command line: `python -m diffrax_vi.bench COMMAND [--quick | --full] [--out DIR]`.

Commands:

- `work-precision`: final error and energy error against wall time, every peer and problem;
- `energy`: energy error over a long horizon (NetworkVI on fixed steps, Tsit5 and Dopri8 at
  several tolerances, so that one of them matches NetworkVI's cost);
- `stability`: the reference's stress sweep of NetworkVI (status per case, rates per
  precision next to the reference's); `--solvers` picks its nonlinear solvers by substring
  (default the reference's two; `--solvers projection` runs the projected step,
  `VariableProjection()`);
- `report`: rebuild `report.md` and the figures from the CSVs in `--out`;
- `all`: the three studies, then the report;
- `long-run`: final error and energy error against wall time over long spans, variational
  solvers against classical peers (`diffrax_vi.bench.long_run`; `--out` defaults to
  `benchmarks/results/long_run`, `--solvers` picks the variational solvers by substring).

Every study streams its rows to a CSV in `--out` as they are measured, so an interrupted run
keeps its partial results. float64 is switched on here (the library itself never does).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time

import jax

CSV = {
    "work-precision": "work_precision.csv",
    "energy": "long_time_energy.csv",
    "stability": "stability.csv",
}


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, file=sys.stderr, dynamic_ncols=True)


def _problems(args, settings) -> list[str]:
    names = args.problems or list(settings)
    unknown = [n for n in names if n not in settings]
    if unknown:
        raise SystemExit(f"unknown problem(s) {unknown}; choose from {sorted(settings)}")
    return names


def _fresh(path: str) -> str:
    if os.path.exists(path):
        os.remove(path)
    return path


def run_work_precision(args) -> None:
    from .harness import work_precision
    from .suites import SETTINGS, networkvi_entries, peer_entries, sweeps

    names = _problems(args, SETTINGS)
    path = _fresh(os.path.join(args.out, CSV["work-precision"]))
    plan = []
    for name in names:
        setting = SETTINGS[name]
        entries = networkvi_entries(setting, args.full) + peer_entries(args.full)
        if args.solvers:
            entries = [e for e in entries if any(s in e.name for s in args.solvers)]
        steps, rtols = sweeps(name, entries, args.full)
        plan.append((name, setting, entries, steps, rtols))
    total = sum(len(v) for *_, s, r in plan for v in (*s.values(), *r.values()))
    bar = _progress(total, "work-precision", not args.no_progress)
    rows: list = []
    for _, setting, entries, steps, rtols in plan:
        rows += work_precision(setting.make(), entries, steps=steps, rtols=rtols,
                               repeats=args.repeats, csv_path=path, progress=bar)
    if bar is not None:
        bar.close()
    from .report import ratio_markdown, ratio_table

    print(ratio_markdown(ratio_table(rows)))


def _energy_problems(chosen, full: bool, settings) -> list[str]:
    """The problems of an energy run: the chosen ones, all with `--full`, else those whose
    setting runs in the quick report (`quick_energy`)."""
    if chosen or full:
        return list(chosen or settings)
    return [n for n, s in settings.items() if s.quick_energy]


def _our_energy_entries(setting, retry: bool) -> list:
    """NetworkVI's entries of the energy study; with `retry` they step with
    `RetryFailedSteps` and carry " retry" in their names."""
    from .suites import energy_entries

    ours = energy_entries(setting)
    if retry:
        ours = [dataclasses.replace(e, name=f"{e.name} retry", retry=True) for e in ours]
    return ours


def run_energy(args) -> None:
    from .harness import Adaptive, long_time_energy
    from .suites import SETTINGS, peer_entries

    _problems(args, SETTINGS)  # refuses unknown names
    names = _energy_problems(args.problems, args.full, SETTINGS)
    path = _fresh(os.path.join(args.out, CSV["energy"]))
    rtols = (1e-8, 1e-10, 1e-12) if args.quick else (1e-6, 1e-8, 1e-10, 1e-12, 1e-14)
    peers = [e for e in peer_entries(False) if isinstance(e, Adaptive)
             and e.name in ("Tsit5", "Dopri8")]
    bar = _progress(len(names) * (2 + len(peers) * len(rtols)), "energy", not args.no_progress)
    for name in names:
        setting = SETTINGS[name]
        n = args.long_steps.get(name, args.long_steps["default"])
        problem = setting.make()
        problem = problem.with_span(problem.t0 + n * setting.long_dt)
        runs = [(e, n) for e in _our_energy_entries(setting, args.retry)]
        runs += [(p, r) for p in peers for r in rtols]
        long_time_energy(problem, runs, csv_path=path, progress=bar,
                         adaptive_max_steps=args.adaptive_max_steps)
    if bar is not None:
        bar.close()


def run_stability(args) -> None:
    from .stability import full_grid, quick_grid, select_solvers, stability_sweep

    try:
        solvers = select_solvers(args.solvers)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    grid = full_grid if args.full else quick_grid
    cases = grid(args.problems, solvers=solvers) if args.problems else grid(solvers=solvers)
    path = os.path.join(args.out, CSV["stability"])
    bar = _progress(len(cases), "stability", not args.no_progress)
    rows = stability_sweep(cases, csv_path=path, progress=bar)
    if bar is not None:
        bar.close()
    from .report import stability_table

    print(stability_table(rows))


def run_long_run(args, argv=None) -> None:
    """The long-run study (`diffrax_vi.bench.long_run`), with its own report in `--out`."""
    from . import long_run

    if args.out is None:
        args.out = long_run.DEFAULT_OUT
    command = "python -m diffrax_vi.bench " + " ".join(sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    long_run.cli(args, command)
    print(f"long-run: {time.perf_counter() - start:.0f} s; report in {args.out}/report.md",
          file=sys.stderr)


def write_report(out: str, command: str = "", elapsed: float | None = None) -> str:
    """Assemble `report.md` and the PNG figures from the CSVs found in `out` (`elapsed`: the
    run's wall time in seconds, stated under the command)."""
    from . import report
    from .harness import read_rows

    parts = ["# diffrax_vi benchmark report", ""]
    if command:
        parts += [f"Command: `{command}`", ""]
    if elapsed is not None:
        parts += [f"Wall time of the run: {elapsed:.0f} s ({elapsed / 60:.1f} min).", ""]
    parts += [
        f"Machine: {platform.platform()}, python {platform.python_version()}, jax "
        f"{jax.__version__} ({jax.default_backend()}), os.cpu_count() = {os.cpu_count()}.",
        "",
    ]
    wp = os.path.join(out, CSV["work-precision"])
    if os.path.exists(wp):
        rows = read_rows(wp)
        report.plot_work_precision(rows, os.path.join(out, "work_precision.png"))
        parts += [
            "## Work-precision", "",
            "Wall time (median after compilation) against the relative error of the final "
            "`q`. ![work-precision](work_precision.png)", "",
            "### Time at equal final error (log-log interpolation on each solver's front)", "",
            report.ratio_markdown(report.ratio_table(rows)), "",
            "### All points", "", report.work_precision_table(rows), "",
        ]
    en = os.path.join(out, CSV["energy"])
    if os.path.exists(en):
        rows = read_rows(en)
        report.plot_energy(rows, os.path.join(out, "long_time_energy.png"))
        parts += [
            "## Long-time energy", "",
            "Running maximum of `|H − H₀|/|H₀|` over the step ends. "
            "![energy](long_time_energy.png)", "",
            report.energy_table(rows), "",
            report.equal_cost_markdown(rows), "",
        ]
    st = os.path.join(out, CSV["stability"])
    if os.path.exists(st):
        rows = read_rows(st)
        report.plot_convergence_heatmap(rows, os.path.join(out, "stability_heatmap.png"))
        parts += [
            "## Stability sweep", "",
            "Converged = status `ok`; `maxiter` and failures count as not converged. The "
            "reference's rates are from its quick run (problems_and_benchmarks §2.6). Every "
            "case runs twice: with our convergence test (a step is converged at a root, up to "
            "its residual floor) and with the reference's (`convergence=\"reference\"`: a "
            "residual `sqrt(eps)` below the seed's once the iterate stops moving, and a stalled "
            "solve returned as converged), which is how the reference's rates were counted. "
            "The heatmap and the status counts use our test. "
            "![heatmap](stability_heatmap.png)", "",
            report.stability_table(rows), "",
        ]
    text = "\n".join(parts)
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(text)
    return text


def _problem_names(study: str, chosen, full: bool = False) -> list[str]:
    if study == "stability":
        from .stability import quick_grid

        names = list(dict.fromkeys(c.problem for c in quick_grid()))
    else:
        from .suites import SETTINGS

        if study == "energy":
            names = _energy_problems(None, full, SETTINGS)
            return [n for n in SETTINGS if n in chosen] if chosen else names
        names = list(SETTINGS)
    return [n for n in names if not chosen or n in chosen]


def _worker_argv(argv: list[str]) -> list[str]:
    """The options every worker inherits: the given ones less command, --out, --problems,
    --jobs (which each worker gets its own of)."""
    out, skip = [], False
    for a in argv[1:]:
        if skip and a.startswith("--"):
            skip = False
        if skip:
            continue
        if a.split("=")[0] in ("--out", "--problems", "--jobs"):
            skip = "=" not in a
            continue
        out.append(a)
    return out


def _cpu_slots(jobs: int) -> list[set[int] | None]:
    """One set of CPUs per worker slot, disjoint where the machine has enough of them.

    Each XLA process sizes its thread pools to the CPUs it may run on, and its threads
    spin while they wait: two unpinned processes on two cores slowed each other down by
    more than 10x in our measurements, which corrupts the timings. `None` leaves a slot
    unpinned (a platform without CPU affinity, or fewer CPUs than jobs)."""
    if not hasattr(os, "sched_getaffinity"):
        return [None] * jobs
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < jobs:
        return [None] * jobs
    return [set(cpus[k::jobs]) for k in range(jobs)]


def _spawn(cmd: list[str], cpus: set[int] | None, **kwargs):
    """`subprocess.Popen(cmd)` restricted to `cpus`: the calling thread takes that affinity
    for the spawn, which the child inherits, and gets its own back."""
    import subprocess

    if cpus is None:
        return subprocess.Popen(cmd, **kwargs)
    own = os.sched_getaffinity(0)
    os.sched_setaffinity(0, cpus)
    try:
        return subprocess.Popen(cmd, **kwargs)
    finally:
        os.sched_setaffinity(0, own)


def run_parallel(args, todo: list[str], argv: list[str]) -> None:
    """Run each (study, problem) as its own `python -m diffrax_vi.bench` process, `--jobs` at
    a time (compilation is single-threaded, so this is what a multi-core machine buys), each
    on its own share of the CPUs (`_cpu_slots`), then concatenate the parts into `--out`.
    Each part keeps its CSV and log under `--out/parts/`; a failed part is reported and the
    others still land."""
    import subprocess

    from .harness import read_rows, write_rows

    tasks = [(study, name) for study in todo
             for name in _problem_names(study, args.problems, args.full)]
    # Long tasks first: the stability sweep and the energy runs outlast a work-precision sweep.
    order = {"stability": 0, "energy": 1, "work-precision": 2}
    tasks.sort(key=lambda t: order[t[0]])
    common = _worker_argv(argv) + ["--no-progress"]
    running: list = []
    failed = []
    parts_dir = os.path.join(args.out, "parts")
    os.makedirs(parts_dir, exist_ok=True)
    done = 0
    free = _cpu_slots(args.jobs)
    while tasks or running:
        while tasks and len(running) < args.jobs:
            study, name = tasks.pop(0)
            cpus = free.pop(0)
            part = os.path.join(parts_dir, f"{study}-{name}")
            os.makedirs(part, exist_ok=True)
            log = open(os.path.join(part, "log.txt"), "w")
            cmd = [sys.executable, "-m", "diffrax_vi.bench", study, "--problems", name,
                   "--out", part, *common]
            proc = _spawn(cmd, cpus, stdout=log, stderr=subprocess.STDOUT)
            running.append((study, name, part, log, proc, cpus))
        time.sleep(0.5)
        for item in list(running):
            study, name, part, log, proc, cpus = item
            if proc.poll() is None:
                continue
            running.remove(item)
            free.append(cpus)
            log.close()
            done += 1
            if proc.returncode != 0:
                failed.append(f"{study} {name} (exit {proc.returncode}, see {part}/log.txt)")
            print(f"[{done}] {study} {name}: exit {proc.returncode}", file=sys.stderr)
    for study in todo:
        path = _fresh(os.path.join(args.out, CSV[study]))
        for name in _problem_names(study, args.problems, args.full):
            part = os.path.join(parts_dir, f"{study}-{name}", CSV[study])
            if os.path.exists(part):
                rows = read_rows(part)
                if rows:
                    write_rows(rows, path, append=True, columns=list(rows[0]))
    if failed:
        print("failed parts: " + "; ".join(failed), file=sys.stderr)


def _long_steps(text: str) -> dict[str, int]:
    out = {"default": 10_000}
    for item in text.split(","):
        if not item:
            continue
        if "=" in item:
            k, v = item.split("=")
            out[k] = int(float(v))
        else:
            out["default"] = int(float(item))
    return out


def main(argv=None) -> None:
    jax.config.update("jax_enable_x64", True)
    parser = argparse.ArgumentParser(
        prog="python -m diffrax_vi.bench", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("command", choices=["work-precision", "energy", "stability", "report",
                                            "all", "long-run"])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="the quick grids (default)")
    mode.add_argument("--full", action="store_true", help="the full grids (hours)")
    parser.add_argument("--out", default=None,
                        help="output folder (default benchmarks/results; long-run: "
                             "benchmarks/results/long_run)")
    parser.add_argument("--problems", nargs="*", help="subset of problems")
    parser.add_argument("--solvers", nargs="*",
                        help="substrings of solver names to keep (stability: of "
                             "LevenbergMarquardt, RegularisedNewton, projection; default the "
                             "first two)")
    parser.add_argument("--spans", type=int, nargs="+", default=None,
                        help="long-run: spans in periods for every problem, instead of the "
                             "quick (100) or full (10^3 to 10^5) ones")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timing repeats after compilation (quick 2, full 5)")
    parser.add_argument("--long-steps", type=_long_steps, default=None,
                        help="NetworkVI steps of the energy runs: N or name=N,... "
                             "(default: 1e4 with --quick, 1e5 with --full)")
    parser.add_argument("--adaptive-max-steps", type=int, default=2**19)
    parser.add_argument("--retry", action="store_true",
                        help="energy: NetworkVI steps with RetryFailedSteps (a failed step "
                             "is taken again in pieces instead of ending the run)")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--jobs", type=int, default=1,
                        help="run the studies as this many parallel processes, one per "
                             "study and problem (default 1: in this process)")
    args = parser.parse_args(argv)
    args.quick = not args.full
    if args.command == "long-run":
        run_long_run(args, argv)
        return
    if args.out is None:
        args.out = "benchmarks/results"
    if args.repeats is None:
        args.repeats = 5 if args.full else 2
    if args.long_steps is None:
        args.long_steps = {"default": 100_000 if args.full else 10_000}
    os.makedirs(args.out, exist_ok=True)
    command = "python -m diffrax_vi.bench " + " ".join(sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    todo = ["work-precision", "energy", "stability"] if args.command == "all" else [args.command]
    runners = {"work-precision": run_work_precision, "energy": run_energy,
               "stability": run_stability}
    if args.jobs < 1:
        raise SystemExit(f"--jobs must be at least 1, got {args.jobs}")
    if args.jobs > 1 and args.command != "report":
        run_parallel(args, todo, list(sys.argv[1:] if argv is None else argv))
        todo = []
    for name in todo:
        if name in runners:
            t, cpu = time.perf_counter(), time.process_time()
            runners[name](args)
            # CPU time approximates the wall time on an unshared machine (compilation and
            # these small solves are essentially single-threaded).
            print(f"{name}: {time.perf_counter() - t:.0f} s wall, "
                  f"{time.process_time() - cpu:.0f} s CPU", file=sys.stderr)
    elapsed = None if args.command == "report" else time.perf_counter() - start
    write_report(args.out, command, elapsed)
    print(f"total {time.perf_counter() - start:.0f} s; report in {args.out}/report.md",
          file=sys.stderr)


if __name__ == "__main__":
    main()
