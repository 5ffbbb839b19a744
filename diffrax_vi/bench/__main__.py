"""Command line: `python -m diffrax_vi.bench COMMAND [--quick | --full] [--out DIR]`.

Commands:

- `work-precision`: final error and energy error against wall time, every peer and problem;
- `energy`: energy error over a long horizon (NetworkVI on fixed steps, Tsit5 and Dopri8 at
  several tolerances, so that one of them matches NetworkVI's cost);
- `stability`: the reference's stress sweep of NetworkVI (status per case, rates per
  precision next to the reference's), with the restated target first: the rates at
  dt <= 1, the dt = 10 cases as accurate / failed / wrong, and those cases again under
  `RetryFailedSteps` (with `--quick`); `--solvers` picks its nonlinear solvers by substring
  (default the reference's two; `--solvers projection` runs the projected step,
  `VariableProjection()`, the default step of `NetworkVI`);
- `report`: rebuild `report.md` and the figures from the CSVs in `--out`;
- `all`: the three studies, then the report.

Where the cases run (`diffrax_vi.bench.executor`): by default on an embedded Dask
`LocalCluster` of one worker per CPU (`--jobs N`: N workers; `--jobs 1`: in this process, no
Dask), or on an existing Dask cluster (`--scheduler ADDRESS`). Every finished case is appended
to `<study>.jsonl` in `--out` as it arrives, and the CSV is written from it; `--resume` keeps
the cases already there, so an interrupted sweep goes on where it stopped. Without the
`distributed` package the cases run in this process. float64 is switched on here (the library
itself never does).
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


class _Executors:
    """The executor of this run: the cases of a sweep run in this process for `--jobs 1` or
    when only one configuration is left to run, else on Dask (`--scheduler`, or an embedded
    `LocalCluster` of `--jobs` workers, one per CPU by default), started on first need and
    closed at the end."""

    def __init__(self, args):
        self.args = args
        self.dask = None

    def run(self, sweep, batches, emit) -> list[str]:
        from .executor import SerialExecutor

        args = self.args
        if args.scheduler is None and (args.jobs == 1 or len(batches) < 2):
            return SerialExecutor().run(sweep, batches, emit)
        return self._dask().run(sweep, batches, emit)

    def _dask(self):
        from .executor import DaskExecutor, SerialExecutor

        args = self.args
        if self.dask is None:
            try:
                self.dask = DaskExecutor(args.scheduler, workers=args.jobs)
            except ImportError as e:
                if args.scheduler is not None:
                    raise SystemExit(str(e)) from None
                print(f"{e}; running the cases in this process", file=sys.stderr)
                self.dask = SerialExecutor()
            except (ConnectionError, ValueError) as e:
                raise SystemExit(str(e)) from None
        return self.dask

    def close(self):
        if self.dask is not None:
            self.dask.close()
            self.dask = None


def _sweep(args, study: str, sweep, cases: list, progress, columns=None) -> list:
    """Run `cases` of `sweep` on the run's executor, logging each case to `<study>.jsonl`
    and streaming its rows to the study's CSV; then rewrite the CSV in case order."""
    from .executor import SweepIncomplete, run_sweep
    from .rows import write_rows

    csv_path = os.path.join(args.out, CSV[study])
    log = os.path.splitext(csv_path)[0] + ".jsonl"
    if not args.resume:
        _fresh(csv_path)

    def stream(case_id, rows):
        if rows:
            write_rows(rows, csv_path, append=True, columns=columns)

    try:
        rows = run_sweep(sweep, cases, executor=args.executors, log=log,
                         resume=args.resume, progress=progress, on_case=stream)
    except SweepIncomplete as e:
        raise SystemExit(f"{study}: {e}") from None
    if rows:
        write_rows(rows, csv_path, columns=columns)
    return rows


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
    from .suites import SETTINGS
    from .sweeps import WorkPrecisionSweep

    names = _problems(args, SETTINGS)
    sweep = WorkPrecisionSweep(full=args.full, repeats=args.repeats)
    keep = (lambda n: any(s in n for s in args.solvers)) if args.solvers else (lambda n: True)
    cases = sweep.cases(names, keep)
    bar = _progress(len(cases), "work-precision", not args.no_progress)
    rows = _sweep(args, "work-precision", sweep, cases, bar)
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
    from .suites import SETTINGS
    from .sweeps import EnergySweep

    _problems(args, SETTINGS)  # refuses unknown names
    names = _energy_problems(args.problems, args.full, SETTINGS)
    rtols = (1e-8, 1e-10, 1e-12) if args.quick else (1e-6, 1e-8, 1e-10, 1e-12, 1e-14)
    sweep = EnergySweep(retry=args.retry, adaptive_max_steps=args.adaptive_max_steps)
    cases = [c for name in names
             for c in sweep.cases(name, args.long_steps.get(name, args.long_steps["default"]),
                                  rtols)]
    bar = _progress(len(cases), "energy", not args.no_progress)
    _sweep(args, "energy", sweep, cases, bar)
    if bar is not None:
        bar.close()


def run_stability(args) -> None:
    from .executor import SweepIncomplete
    from .stability import full_grid, quick_grid, select_solvers, stability_sweep

    try:
        solvers = select_solvers(args.solvers)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    grid = full_grid if args.full else quick_grid
    cases = grid(args.problems, solvers=solvers) if args.problems else grid(solvers=solvers)
    path = os.path.join(args.out, CSV["stability"])
    bar = _progress(len(cases), "stability", not args.no_progress)
    try:
        rows = stability_sweep(cases, csv_path=path, progress=bar, executor=args.executors,
                               log=os.path.splitext(path)[0] + ".jsonl", resume=args.resume)
    except SweepIncomplete as e:
        raise SystemExit(f"stability: {e}") from None
    if bar is not None:
        bar.close()
    from .report import stability_table

    print(stability_table(rows))


def write_report(out: str, command: str = "", elapsed: float | None = None) -> str:
    """Assemble `report.md` and the PNG figures from the CSVs found in `out` (`elapsed`: the
    run's wall time in seconds, stated under the command)."""
    from . import report
    from .rows import read_rows

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
            "The heatmap and the status counts use our test. The restated target (issue 52) "
            "comes first: our test's rate over the cases with dt <= 1; each dt = 10 case "
            "accurate (successful, final q within 1 % of the motion's size of the reference, "
            "or sqrt(eps) where larger), failed (a non-successful result) or wrong "
            "(successful, not accurate); and the same cases under `RetryFailedSteps`. "
            "![heatmap](stability_heatmap.png)", "",
            report.stability_table(rows), "",
        ]
    text = "\n".join(parts)
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(text)
    return text


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
                                            "all"])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="the quick grids (default)")
    mode.add_argument("--full", action="store_true", help="the full grids (hours)")
    parser.add_argument("--out", default=None,
                        help="output folder (default benchmarks/results)")
    parser.add_argument("--problems", nargs="*", help="subset of problems")
    parser.add_argument("--solvers", nargs="*",
                        help="substrings of solver names to keep (stability: of "
                             "LevenbergMarquardt, RegularisedNewton, projection; default the "
                             "first two)")
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
    parser.add_argument("--jobs", type=int, default=None,
                        help="workers of the embedded Dask cluster (default: one per CPU); "
                             "1: run the cases in this process")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="send the cases to the Dask scheduler at ADDRESS "
                             "(e.g. tcp://10.0.0.5:8786) instead of an embedded cluster")
    parser.add_argument("--resume", action="store_true",
                        help="keep the finished cases of <study>.jsonl in --out and run "
                             "only the others")
    args = parser.parse_args(argv)
    args.quick = not args.full
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
    if args.jobs is not None and args.jobs < 1:
        raise SystemExit(f"--jobs must be at least 1, got {args.jobs}")
    args.executors = _Executors(args)
    try:
        for name in todo:
            if name in runners:
                t = time.perf_counter()
                runners[name](args)
                print(f"{name}: {time.perf_counter() - t:.0f} s wall", file=sys.stderr)
    finally:
        args.executors.close()
    elapsed = None if args.command == "report" else time.perf_counter() - start
    write_report(args.out, command, elapsed)
    print(f"total {time.perf_counter() - start:.0f} s; report in {args.out}/report.md",
          file=sys.stderr)


if __name__ == "__main__":
    main()
