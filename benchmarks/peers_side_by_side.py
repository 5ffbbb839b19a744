"""heyoka and our solvers side by side, in one process (issue 50): final error against wall time.

1. Kepler, e = 0.5, 100 orbits (T = 200π): final position error (max norm) against the exact
   solution of `problems.kepler`.
2. Hénon–Heiles, q0 = p0 = (0.1, 0.1), T = 100: final state error (max norm over q and p)
   against heyoka in quadruple precision (`heyoka.real128`, tol 1e-32), itself checked
   against heyoka in long double (tol 1e-19); the difference of the two is printed.
3. 256 Kepler members (e evenly spread over [0.1, 0.6], 10 orbits each): member-orbits per
   second and the largest final position error, for heyoka as a loop over one integrator,
   `ensemble_propagate_until` on `--threads` threads and its SIMD batch mode, against
   `jax.vmap` of `CGVI(k)` and of `Dopri8`.

Solvers: heyoka at tol 1e-12 and 1e-15 (its integrator built once per tolerance, without
heyoka's compiled-code caches, and its build reported as "compile"); `dvi.CGVI(k)` over a grid
of degrees and steps; `diffrax.Dopri8` at rtol = atol = 1e-13. Ours are `jax.jit` around the
whole `diffeqsolve(..., saveat=SaveAt(t1=True))`, the step a Python constant; "compile" is the
first call less the best run. Every time is the best of `--repeats` runs after a warm-up (the
median beside it). For each heyoka tolerance the summary names the CGVI configuration at least
as accurate (both below 1e-14 counts as equal) of the smallest median time, and the ratio of
its median to heyoka's median (the ratio of the best times beside it). The default `CGVI` takes
the Jacobian-free iteration on these problems (a constant kinetic matrix) since 2026-12-01, so
`--engine` now builds the same solver as the default; it is kept for the older commands. The
load average of the machine is printed at the start and at the end.

    .venv/bin/python -m benchmarks.peers_side_by_side [--quick] [--out FILE] [--repeats 5]
        [--members 256] [--threads 2] [--only kepler henon_heiles ensemble] [--degrees 6 8]
        [--engine] [--whole-loops BYTES]

`--whole-loops 100000000` calls `diffrax_vi.compile_loops_whole(100000000)` before the first
JAX computation: XLA's CPU backend then compiles a solve whose loop holds no library call as
one function (the benchmarks page). The same comes from the environment, with
`XLA_FLAGS=--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000`.

`--quick` is a smoke run (2 orbits, T = 10, 8 members over one orbit, one CGVI configuration
per section); its time is mostly the compilation of the three CGVI solves.

Needs heyoka (`pip install "diffrax_vi[peers]"`).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import peers  # noqa: E402

EQUAL_BELOW = 1e-14  # two errors both below this count as equal
HEYOKA_TOLS = (1e-12, 1e-15)
DOPRI8_RTOL = 1e-13

# CGVI degree -> steps per orbit (Kepler) and step sizes (Hénon–Heiles).
KEPLER_GRID = {4: (128, 256), 6: (32, 64, 128), 8: (24, 32, 64), 10: (16, 24, 32)}
HH_GRID = {4: (0.1, 0.25), 6: (0.25, 0.5, 1.0), 8: (0.5, 1.0, 2.0), 10: (1.0, 2.0, 4.0)}
ENSEMBLE_CGVI = ((6, 64), (8, 32))  # (degree, steps per orbit) under vmap

QUICK = dict(kepler_orbits=2, hh_t1=10.0, kepler_grid={6: (32,)}, hh_grid={6: (0.5,)},
             ensemble_cgvi=((6, 32),), members=8, ensemble_orbits=1)
FULL = dict(kepler_orbits=100, hh_t1=100.0, kepler_grid=KEPLER_GRID, hh_grid=HH_GRID,
            ensemble_cgvi=ENSEMBLE_CGVI, members=256, ensemble_orbits=10)


class Out:
    """Lines to stdout as they come, and to a file at the end."""

    def __init__(self):
        self.lines: list[str] = []

    def __call__(self, text: str = "") -> None:
        print(text, flush=True)
        self.lines.append(text)

    def save(self, path: str) -> None:
        with open(path, "w", encoding="utf-8") as f:
            f.write("\n".join(self.lines) + "\n")


def timed_jax(fn, *args, repeats: int):
    """`(output, compile_s, best_s, median_s)`: a first (compiling) call, then `repeats`."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    best = min(times)
    return out, max(first - best, 0.0), best, statistics.median(times)


def fixed_solve(problem, solver, h: float, steps: int):
    """`jit` of the whole constant-step solve to `problem.t1`, final state only."""
    term, t0, t1 = problem.term, problem.t0, problem.t1

    @jax.jit
    def solve(y0):
        sol = diffrax.diffeqsolve(term, solver, t0, t1, h, y0, args=problem.args,
                                  saveat=diffrax.SaveAt(t1=True), max_steps=steps + 2,
                                  throw=False)
        return sol.ys, sol.result == diffrax.RESULTS.successful, sol.stats["num_steps"]

    return solve


def dopri8_solve(problem, rtol: float):
    term, t0, t1 = problem.term.to_ode(), problem.t0, problem.t1

    @jax.jit
    def solve(y0):
        sol = diffrax.diffeqsolve(term, diffrax.Dopri8(), t0, t1, None, y0, args=problem.args,
                                  stepsize_controller=diffrax.PIDController(rtol=rtol,
                                                                            atol=rtol),
                                  saveat=diffrax.SaveAt(t1=True), max_steps=2**22, throw=False)
        return sol.ys, sol.result == diffrax.RESULTS.successful, sol.stats["num_steps"]

    return solve


def error_of(q, p, reference, what: str) -> float:
    q_ref, p_ref = reference
    err = np.max(np.abs(np.asarray(q, np.longdouble) - q_ref))
    if what == "state":
        err = max(err, np.max(np.abs(np.asarray(p, np.longdouble) - p_ref)))
    return float(err)


def fmt_s(seconds: float) -> str:
    return f"{seconds * 1e3:.3f} ms" if seconds < 1 else f"{seconds:.2f} s"


def header(out: Out, argv) -> None:
    hy = peers.require_heyoka()
    out(f"# heyoka and diffrax_vi side by side ({datetime.date.today()}, "
        f"{platform.machine()}, {os.cpu_count()} CPUs, python {platform.python_version()})")
    out(f"# jax {jax.__version__}, diffrax {diffrax.__version__}, heyoka "
        f"{getattr(hy, '__version__', '?')}; float64; one process; command: python -m "
        f"benchmarks.peers_side_by_side {' '.join(argv)}".rstrip())
    out(f"# XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    out(f"# load average at the start (1, 5, 15 min): {load_average()}")


def load_average() -> str:
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:  # not on every platform
        return "unknown"


def table_header(out: Out) -> None:
    out(f"{'solver':<24} {'setting':<16} {'steps':>7} {'error':>9} {'best':>11} "
        f"{'median':>11} {'compile':>9} status")


def row(out: Out, solver, setting, steps, err, best, median, compile_s, status="ok"):
    err_text = f"{err:9.2e}" if err is not None and math.isfinite(err) else f"{'-':>9}"
    out(f"{solver:<24} {setting:<16} {steps:>7} {err_text} {fmt_s(best):>11} "
        f"{fmt_s(median):>11} {compile_s:8.2f}s {status}")


def cgvi(degree: int, config: dict):
    """`CGVI(degree)`, with the Jacobian-free engine where `--engine` asked for it."""
    if config.get("engine"):
        return dvi.CGVI(degree, root_finder=dvi.ChordIteration(ftol=0.0, predict=True,
                                                                    picard=True))
    return dvi.CGVI(degree)


def compare(problem_name: str, problem, reference, what: str, config: dict, grid: dict,
            repeats: int, out: Out, step_label) -> dict:
    """heyoka, CGVI over `grid` and Dopri8 on `problem`; returns the rows for the summary."""
    results = {"heyoka": [], "cgvi": [], "dopri8": []}
    out()
    out(f"## {problem_name}: {what} error at t1 = {problem.t1:g}")
    table_header(out)
    for tol in HEYOKA_TOLS:
        peer = peers.HeyokaPeer(problem, tol)
        run = peer.timed_run(repeats=repeats, reference=False)
        err = error_of(run.q, run.p, reference, what)
        row(out, f"heyoka (order {peer.order})", f"tol {tol:g}", run.steps, err, run.wall_s,
            run.median_s, peer.compile_s, run.outcome.replace("time_limit", "ok"))
        results["heyoka"].append(dict(tol=tol, error=err, wall_s=run.wall_s,
                                      median_s=run.median_s, compile_s=peer.compile_s))
    span = problem.t1 - problem.t0
    for degree, settings in grid.items():
        for setting in settings:
            h, steps, label = step_label(setting, span)
            solve = fixed_solve(problem, cgvi(degree, config), h, steps)
            try:
                ((q, p), ok, taken), compile_s, best, median = timed_jax(
                    solve, problem.y0, repeats=repeats)
            except Exception as e:  # a configuration that cannot run is a row, not the end
                out(f"CGVI({degree}) {label}: {type(e).__name__}: {str(e).splitlines()[0]}")
                continue
            err = error_of(q, p, reference, what)
            status = "ok" if bool(ok) and math.isfinite(err) else "failed"
            row(out, f"CGVI({degree})", label, int(taken), err, best, median, compile_s,
                status)
            if status == "ok":
                results["cgvi"].append(dict(name=f"CGVI({degree}) {label}", error=err,
                                            wall_s=best, median_s=median))
    solve = dopri8_solve(problem, DOPRI8_RTOL)
    ((q, p), ok, taken), compile_s, best, median = timed_jax(solve, problem.y0, repeats=repeats)
    err = error_of(q, p, reference, what)
    row(out, "Dopri8", f"rtol {DOPRI8_RTOL:g}", int(taken), err, best, median, compile_s,
        "ok" if bool(ok) else "failed")
    results["dopri8"].append(dict(error=err, wall_s=best, median_s=median))
    return results


def summary(problem_name: str, results: dict, out: Out) -> None:
    for dop in results["dopri8"]:
        out(f"{problem_name}, Dopri8 rtol {DOPRI8_RTOL:g}: {dop['error']:.1e} in "
            f"{fmt_s(dop['median_s'])} median")
    for hey in results["heyoka"]:
        ok = [r for r in results["cgvi"]
              if r["error"] <= hey["error"] or (r["error"] < EQUAL_BELOW
                                                and hey["error"] < EQUAL_BELOW)]
        head = (f"{problem_name}, heyoka tol {hey['tol']:g} ({hey['error']:.1e} in "
                f"{fmt_s(hey['median_s'])} median): ")
        if not ok:
            out(head + "no CGVI configuration of the grid is as accurate")
            continue
        best = min(ok, key=lambda r: r["median_s"])
        out(head + f"fastest CGVI as accurate: {best['name']} ({best['error']:.1e} in "
            f"{fmt_s(best['median_s'])} median), {best['median_s'] / hey['median_s']:.1f}x "
            f"heyoka's median time ({best['wall_s'] / hey['wall_s']:.1f}x by best times)")


def kepler_section(config: dict, repeats: int, out: Out) -> dict:
    orbits = config["kepler_orbits"]
    problem = problems.kepler(0.5, t1=2 * math.pi * orbits, dtype=jnp.float64)
    q_ref, p_ref = problem.reference(np.array([problem.t1]))
    reference = (q_ref[0].astype(np.longdouble), p_ref[0].astype(np.longdouble))

    def label(per_orbit, span):
        steps = per_orbit * orbits
        return span / steps, steps, f"h = 2pi/{per_orbit}"

    return compare(f"Kepler e = 0.5, {orbits} orbits", problem, reference, "position",
                   config, config["kepler_grid"], repeats, out, label)


def henon_heiles_section(config: dict, repeats: int, out: Out) -> dict:
    hy = peers.require_heyoka()
    problem = problems.henon_heiles(q0=(0.1, 0.1), p0=(0.1, 0.1), t1=config["hh_t1"],
                                    dtype=jnp.float64)
    quad = peers.HeyokaPeer(problem, 1e-32, fp_type=hy.real128)
    ref = quad.timed_run(repeats=1, warmup=0, reference=False)
    ld = peers.HeyokaPeer(problem, 1e-19, fp_type=np.longdouble)
    check = ld.timed_run(repeats=1, warmup=0, reference=False)
    gap = max(np.max(np.abs(check.q - ref.q)), np.max(np.abs(check.p - ref.p)))
    out()
    out(f"# Henon-Heiles reference: heyoka real128 tol 1e-32 (order {quad.order}, "
        f"{ref.steps} steps, built in {quad.compile_s:.2f} s); long double tol 1e-19 differs "
        f"by {float(gap):.1e}")

    def label(h, span):
        steps = round(span / h)
        return span / steps, steps, f"h = {h:g}"

    return compare(f"Henon-Heiles q0 = p0 = (0.1, 0.1), T = {problem.t1:g}", problem,
                   (ref.q, ref.p), "state", config, config["hh_grid"], repeats, out, label)


def ensemble_section(config: dict, repeats: int, threads: int, out: Out) -> None:
    members, orbits = config["members"], config["ensemble_orbits"]
    t1 = 2 * math.pi * orbits
    e, y0s = peers.kepler_members(members)
    exact = peers.kepler_positions(e, t1)
    out()
    out(f"## Ensemble: {members} Kepler members, e in [0.1, 0.6], {orbits} orbits each; "
        f"largest final position error")
    out(f"{'solver':<40} {'member-orbits/s':>16} {'error':>9} {'best':>11} {'median':>11} "
        f"{'compile':>9}   (member-orbits/s from the median)")

    def line(name, best, median, err, compile_s):
        out(f"{name:<40} {members * orbits / median:16.0f} {err:9.2e} {fmt_s(best):>11} "
            f"{fmt_s(median):>11} {compile_s:8.2f}s")

    heyoka_best = {}
    for tol in HEYOKA_TOLS:
        peer = peers.HeyokaPeer(problems.kepler(0.5, t1=t1, dtype=jnp.float64), tol)
        for method in ("loop", "ensemble", "batch"):
            run = peer.propagate_many(y0s, t1, method=method, threads=threads,
                                      repeats=repeats)
            err = float(np.max(np.abs(run.states[:, :2] - exact)))
            name = {"loop": "heyoka loop (1 core)",
                    "ensemble": f"heyoka ensemble ({threads} threads)",
                    "batch": "heyoka batch (SIMD, 1 core)"}[method]
            line(f"{name} tol {tol:g}", run.wall_s, run.median_s, err, peer.compile_s)
            if method != "batch":
                current = heyoka_best.get(tol)
                if current is None or run.median_s < current[1]:
                    heyoka_best[tol] = (name, run.median_s, err)
    term = problems.kepler(0.5, dtype=jnp.float64).term
    y0 = (jnp.asarray(y0s[:, :2]), jnp.asarray(y0s[:, 2:]))
    ours = []
    for degree, per_orbit in config["ensemble_cgvi"]:
        steps = per_orbit * orbits
        h = t1 / steps
        solver = cgvi(degree, config)

        def member(y, solver=solver, h=h, steps=steps):
            sol = diffrax.diffeqsolve(term, solver, 0.0, t1, h, y,
                                      saveat=diffrax.SaveAt(t1=True), max_steps=steps + 2)
            return sol.ys[0][-1]

        run = jax.jit(jax.vmap(member))
        q, compile_s, best, median = timed_jax(run, y0, repeats=repeats)
        err = float(np.max(np.abs(np.asarray(q) - exact)))
        line(f"vmap CGVI({degree}) h = 2pi/{per_orbit}", best, median, err, compile_s)
        ours.append((f"CGVI({degree}) h = 2pi/{per_orbit}", median, err))

    def dopri(y):
        sol = diffrax.diffeqsolve(
            term.to_ode(), diffrax.Dopri8(), 0.0, t1, None, y,
            stepsize_controller=diffrax.PIDController(rtol=DOPRI8_RTOL, atol=DOPRI8_RTOL),
            saveat=diffrax.SaveAt(t1=True), max_steps=2**20)
        return sol.ys[0][-1]

    q, compile_s, best, median = timed_jax(jax.jit(jax.vmap(dopri)), y0, repeats=repeats)
    err = float(np.max(np.abs(np.asarray(q) - exact)))
    line(f"vmap Dopri8 rtol {DOPRI8_RTOL:g}", best, median, err, compile_s)
    out()
    for tol in HEYOKA_TOLS:
        target = heyoka_best[tol]
        rate = members * orbits / target[1]
        out(f"heyoka's best at tol {tol:g} (loop or ensemble_propagate_until, by median): "
            f"{target[0]}, {rate:.0f} member-orbits/s at {target[2]:.1e}")
        for name, median, err in ours:
            verdict = "as accurate" if err <= target[2] or max(err, target[2]) < EQUAL_BELOW \
                else "less accurate"
            out(f"  vmap {name}: {members * orbits / median:.0f} member-orbits/s by median "
                f"({target[1] / median:.2f}x heyoka's rate), {verdict}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="a smoke run: 2 orbits, T = 10, one CGVI configuration each, "
                             "8 members over 1 orbit")
    parser.add_argument("--engine", action="store_true",
                        help="CGVI with ChordIteration(ftol=0, predict=True, picard=True)")
    parser.add_argument("--out", default=None, help="also write the tables to this file")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed runs after the warm-up (default 5; 2 with --quick)")
    parser.add_argument("--members", type=int, default=None)
    parser.add_argument("--threads", type=int, default=2,
                        help="threads of heyoka's ensemble_propagate_until")
    parser.add_argument("--only", nargs="+", choices=("kepler", "henon_heiles", "ensemble"),
                        default=("kepler", "henon_heiles", "ensemble"))
    parser.add_argument("--degrees", type=int, nargs="*", default=None,
                        help="only these CGVI degrees (none: no CGVI)")
    parser.add_argument(
        "--whole-loops", type=int, default=0, metavar="BYTES",
        help="let XLA's CPU backend compile a while loop whose one pass touches fewer than "
             "BYTES bytes as one function (dvi.compile_loops_whole(BYTES), before the first "
             "JAX computation; a setting of this whole process)",
    )
    args = parser.parse_args(argv)
    if args.whole_loops:
        dvi.compile_loops_whole(args.whole_loops)
    config = dict(QUICK if args.quick else FULL)
    if args.degrees is not None:
        keep = set(args.degrees)
        for key in ("kepler_grid", "hh_grid"):
            config[key] = {k: v for k, v in config[key].items() if k in keep}
        config["ensemble_cgvi"] = tuple(c for c in config["ensemble_cgvi"] if c[0] in keep)
    if args.members is not None:
        config["members"] = args.members
    config["engine"] = args.engine
    repeats = args.repeats if args.repeats is not None else (2 if args.quick else 5)
    if repeats < 1:
        parser.error("--repeats must be at least 1")
    out = Out()
    header(out, sys.argv[1:] if argv is None else argv)
    found = {}
    if "kepler" in args.only:
        found["Kepler"] = kepler_section(config, repeats, out)
    if "henon_heiles" in args.only:
        found["Henon-Heiles"] = henon_heiles_section(config, repeats, out)
    if found:
        out()
        out("## At equal error (both below 1e-14 count as equal)")
        for name, results in found.items():
            summary(name, results, out)
    if "ensemble" in args.only:
        ensemble_section(config, repeats, args.threads, out)
    out()
    out(f"# load average at the end (1, 5, 15 min): {load_average()}")
    if args.out:
        out.save(args.out)


if __name__ == "__main__":
    main()
