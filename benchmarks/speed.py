"""Every speed figure of the performance issues in one run: medians of repeats and ratios.

1. Time per step of `NetworkVI(ShallowNetBasis(tanh, 10), GaussLegendre(8))` on the harmonic
   oscillator (float64, h = 0.1, `--ho-steps` steps, default 1000), with the error of q at
   the end relative to the amplitude, and the median nonlinear iterations per step;
2. the same for the double pendulum with `GaussLegendre(16)`: every configuration over
   `DP_COMPARE_STEPS` (20) steps, which all of them run, and over `--dp-steps` (default 100,
   to t = 10, as far as the stored reference is good to many digits), where the
   all-parameter configurations fail (the table gives the time they reach);
   each in the configurations of `CONFIGS` side by side: the default (variable projection,
   `VariableProjection()` with `RoundoffNewton()`), and the reference's all-parameter
   formulation (`FreeEndpoints()`, Levenberg–Marquardt) as it was the default, in its fast
   configuration (refitted neurons as seeds, the closed-form Jacobian and a solve ended by
   the first settled exact iteration) and with that stopping rule alone (`early-stop`);
   then the ratios of every configuration against the default (time per step, iterations,
   error, compile) and whether the default dominates it;
3. first-call time (trace + compile + one run) minus one steady-state run of a ShallowNet
   `diffeqsolve`, per fixture;
4. ensembles of oscillator trajectories (10 steps each, random amplitudes, the default
   solver) through `dvi.ensemble` against a Python loop of single jitted solves (timed on
   `--loop-sample` members, its throughput extrapolated): `--members` (default 1024) with the
   default `batch_size=None` (full vmap, lockstep) and with `batch_size=1` (a compiled loop
   over members), and `--vmap-members` (default 128) with `batch_size=None`;
5. the floor of that ensemble on this machine: the linear solve of one Newton iteration of
   the projected step (an LU solve, `jnp.linalg.solve`, of the square reduced Jacobian,
   `k·D + D` unknowns: `k = min(S, R + 1)` span coefficients per coordinate and
   `p_{n+1}`), vmapped over `--members` members, per member, times the iterations of a
   member's solve: what a member would cost if its steps did nothing but an LU solve per
   iteration (no Jacobian, no residuals), the bound on an ensemble's throughput that the
   issues set; each ensemble's throughput as a fraction of that bound, the floor timed in
   the same rounds as the ensemble (median over rounds of the ratio), compiled with the CPU
   options `dvi.ensemble` uses, as the ensembles are. (The projected step's own inverse, by
   elimination over all members at once, costs less than that LU solve, so a fraction above
   100 % is possible);
6. with `--devices 8` (default), the same ensemble sharded over 8 virtual CPU devices in a
   subprocess (`XLA_FLAGS=--xla_force_host_platform_device_count=8`), its time and the
   largest difference from the unsharded result.

    .venv/bin/python -m benchmarks.speed [--quick] [--only fixtures|ensembles]

`--only fixtures` runs sections 1-3, `--only ensembles` sections 4-6.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import statistics
import subprocess
import sys
import time

if "--sharded-child" in sys.argv:  # must set the device count before JAX starts
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8"
    ).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.common import ROOT, command_line, module_command  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import iteration_summary, timed  # noqa: E402
from diffrax_vi.ensemble import cpu_compiler_options  # noqa: E402

H = 0.1
# The double pendulum's comparison of all configurations: at h = 0.1 the all-parameter
# solves stall on a step between t = 2.1 and t = 3.5 (the fast configuration last), and the
# projected default runs on to t = 20 at least (200 steps; measured).
DP_COMPARE_STEPS = 20

_LM_EARLY_STOP = dict(jacobian="auto", settle=0, otol=2.0**-39)

# The configurations compared, each with its formulation: the default (variable projection:
# a fixed hidden layer, the output weights solved on its orthonormalised span, `k·D + D`
# unknowns, plain Newton to round-off); the reference's all-parameter formulation (the old
# default: the reference's seed on every step, a fresh Jacobian on every iteration, a stalled
# residual for 3 iterations before settled outputs end a solve); its old fast configuration
# (the previous step's neurons refitted as seed, the closed-form Jacobian, and a solve ended
# by the first exact iteration whose outputs moved by at most eps^(3/4)); and `early-stop`:
# that stopping rule and Jacobian with the default seed (the OGA fit on every step). The
# all-parameter rows "jacrev" and "auto" of the results before the projected default (the
# Jacobian by `jax.jacrev`, or in closed form alone) changed the time per step (closed form:
# 0.28x on the double pendulum) but neither the median iterations nor the error's order.
CONFIGS = {
    "default": dict(),
    "all-parameter": dict(formulation=dvi.FreeEndpoints()),
    "fast": dict(
        formulation=dvi.FreeEndpoints(),
        seed=dvi.SeedPolicy(reuse_neurons=True),
        root_finder=dvi.LevenbergMarquardt(**_LM_EARLY_STOP),
    ),
    "early-stop": dict(
        formulation=dvi.FreeEndpoints(), root_finder=dvi.LevenbergMarquardt(**_LM_EARLY_STOP)
    ),
}
# what each configuration is, for the tables
LABELS = {
    "default": "VariableProjection, RoundoffNewton",
    "all-parameter": "FreeEndpoints, LevenbergMarquardt",
    "fast": "FreeEndpoints, LevenbergMarquardt (auto, settle 0), refit seeds",
    "early-stop": "FreeEndpoints, LevenbergMarquardt (auto, settle 0)",
}


def fixture_run(problem, nodes, steps, repeats, config):
    problem = problem.with_span(n_steps=steps, dt=H)
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(nodes), **CONFIGS[config]
    )

    @eqx.filter_jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term,
            solver,
            problem.t0,
            problem.t1,
            H,
            y0,
            args=problem.args,
            saveat=diffrax.SaveAt(t1=True, solver_state=True),
            max_steps=steps + 1,
            throw=False,
        )

    sol, first = timed(run, problem.y0)
    total = statistics.median(timed(run, problem.y0)[1] for _ in range(repeats))
    ok = bool(sol.result == diffrax.RESULTS.successful)
    its = iteration_summary(sol.solver_state)
    error = None  # a failed solve saves no end state
    if ok:
        t_end = float(sol.ts[-1])
        amplitude = float(np.max(np.abs(problem.reference(problem.ts)[0])))
        q_ref = problem.reference(np.array([t_end]))[0][0]
        error = float(np.max(np.abs(np.asarray(sol.ys[0][-1]) - q_ref))) / amplitude
    return dict(
        ok=ok,
        steps=its["steps"],
        t_end=float(problem.t0) + its["steps"] * H,
        us_step=1e6 * total / max(its["steps"], 1),
        compile_s=first - total,
        error=error,
        it_median=its["it_median"],
        it_mean=its["it_mean"],
    )


def ensemble_inputs(members):
    rng = np.random.default_rng(0)
    q = jnp.asarray(rng.uniform(0.1, 1.0, (members, 1)))
    return q, jnp.zeros_like(q)


_HO = problems.harmonic_oscillator(dtype=jnp.float64)
_NODES = 8
_SOLVER = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(_NODES))


def solve_member(y0):
    sol = diffrax.diffeqsolve(
        _HO.term, _SOLVER, 0.0, 1.0, H, y0, saveat=diffrax.SaveAt(t1=True), throw=False
    )
    return sol.ys, sol.result == diffrax.RESULTS.successful


def ensemble_figures(members, vmap_members, loop_sample, repeats, floor=None):
    """Throughput of `dvi.ensemble` (members per second) against a Python loop of single
    jitted solves: the default full `vmap` (`batch_size=None`, lockstep) on `members` and on
    `vmap_members` members, and one member after another (`batch_size=1`) on `members`. With
    `floor` (a callable timing the floor once: seconds per member), each round times the
    floor right after the ensemble, and a row's `floor_fraction` is the median over rounds
    of the floor's time against the ensemble's, per member: a change in the machine's speed
    between rounds touches both alike."""
    y0 = ensemble_inputs(max(members, vmap_members))
    single = jax.jit(solve_member)
    jax.block_until_ready(single((y0[0][0], y0[1][0])))
    loops = []
    for _ in range(repeats):
        start = time.perf_counter()
        for i in range(loop_sample):
            jax.block_until_ready(single((y0[0][i], y0[1][i])))
        loops.append((time.perf_counter() - start) / loop_sample)
    per_loop = statistics.median(loops)
    rows = []
    runs = [(None, members), (1, members)]
    if vmap_members != members:
        runs.append((None, vmap_members))
    for mode, n in runs:
        y = (y0[0][:n], y0[1][:n])
        run = functools.partial(dvi.ensemble, solve_member, batch_size=mode)
        out, first = timed(run, y)
        times, fractions = [], []
        for _ in range(repeats):
            times.append(timed(run, y)[1])
            if floor is not None:
                fractions.append(floor() * n / times[-1])
        t_ens = statistics.median(times)
        # every member against its own single solve (the first loop_sample of them)
        (q, _), ok = out
        diff = max(
            float(np.max(np.abs(np.asarray(q[i]) - np.asarray(single((y[0][i], y[1][i]))[0][0]))))
            for i in range(min(loop_sample, n))
        )
        rows.append(dict(
            mode=mode,
            members=n,
            ok=bool(np.all(np.asarray(ok))),
            ens_s=t_ens,
            ens_compile_s=first - t_ens,
            speedup=per_loop * n / t_ens,
            floor_fraction=statistics.median(fractions) if fractions else None,
            diff=diff,
        ))
    return per_loop, rows


def floor_timer(members):
    """The floor of one ensemble member (see `linear_solve_floor`) as a callable that times
    it once (seconds per member, for all the iterations of a member's solve), with the
    iterations of a member's solve and `k·D + D`."""
    formulation = _SOLVER.formulation
    assert isinstance(formulation, dvi.VariableProjection), formulation
    y0 = ensemble_inputs(1)
    dim = y0[0].shape[1]
    sol = diffrax.diffeqsolve(
        _HO.term, _SOLVER, 0.0, 1.0, H, (y0[0][0], y0[1][0]),
        saveat=diffrax.SaveAt(t1=True, solver_state=True),
    )
    iterations = int(sol.solver_state.iterations)
    k = formulation.span_rank(_SOLVER.basis, _NODES)
    n = k * dim + dim  # span coefficients and p_{n+1}
    rng = np.random.default_rng(1)
    jac = jnp.asarray(rng.standard_normal((members, n, n)))
    rhs = jnp.asarray(rng.standard_normal((members, n)))
    options = dict(cpu_compiler_options()) if jax.default_backend() == "cpu" else {}
    solve = jax.jit(jax.vmap(jnp.linalg.solve), compiler_options=options)
    jax.block_until_ready(solve(jac, rhs))

    def once():
        return timed(solve, jac, rhs)[1] / members * iterations

    return once, iterations, n


def linear_solve_floor(members, repeats, timer=None):
    """Seconds per member of the linear solve of one Newton iteration of the projected step
    (LU of the square reduced Jacobian, `k·D + D` unknowns), vmapped over `members` members
    of the ensemble's size; the nonlinear iterations of one member's solve; and `k·D + D`.
    `timer`: what `floor_timer(members)` returned, where the caller has it already."""
    once, iterations, n = floor_timer(members) if timer is None else timer
    per_member = statistics.median(once() for _ in range(5 * repeats)) / iterations
    return per_member, iterations, n


def sharded_child(members, repeats):
    assert jax.device_count() == 8, jax.devices()
    y0 = ensemble_inputs(members)
    mesh = dvi.ensemble_mesh()
    ref = jax.block_until_ready(dvi.ensemble(solve_member, y0))
    out = jax.block_until_ready(dvi.ensemble(solve_member, y0, mesh=mesh))
    t_sh = statistics.median(
        timed(lambda y: dvi.ensemble(solve_member, y, mesh=mesh), y0)[1] for _ in range(repeats)
    )
    t_un = statistics.median(
        timed(lambda y: dvi.ensemble(solve_member, y), y0)[1] for _ in range(repeats)
    )
    diff = max(
        float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
        for a, b in zip(
            jax.tree_util.tree_leaves(out[0]), jax.tree_util.tree_leaves(ref[0]), strict=True
        )
    )
    devices = len(jax.tree_util.tree_leaves(out[0])[0].sharding.device_set)
    print(f"SHARDED {t_sh} {t_un} {diff} {devices} {bool(np.all(np.asarray(out[1])))}")


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--ho-steps", type=int, default=1000)
    # 100 steps (t <= 10, the span of the stored reference): the projected default runs the
    # double pendulum at h = 0.1 to t = 20 at least (200 steps, 2.5 iterations per step, at
    # most 5), where the all-parameter solves stall between t = 2.1 and 3.5 (see
    # DP_COMPARE_STEPS); beyond t = 10 the motion is chaotic and no reference is good to many
    # digits.
    parser.add_argument("--dp-steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--members", type=int, default=1024)
    parser.add_argument("--vmap-members", type=int, default=128, help="for batch_size=None")
    parser.add_argument("--loop-sample", type=int, default=16)
    parser.add_argument("--devices", type=int, default=8, help="0 skips the sharded run")
    parser.add_argument("--quick", action="store_true", help="100/20 steps, 128 members")
    parser.add_argument(
        "--only", choices=("fixtures", "ensembles"), default=None,
        help="run sections 1-3 (fixtures) or 4-6 (ensembles, floor, sharding) alone",
    )
    parser.add_argument("--sharded-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.quick:
        args.ho_steps, args.dp_steps, args.members, args.loop_sample = 100, 20, 128, 8
        args.vmap_members = 32
    if args.sharded_child:
        sharded_child(args.members, args.repeats)
        return

    print(f"command: {command_line('benchmarks.speed')}")
    print(
        f"machine: {platform.platform()}, python {platform.python_version()}, jax "
        f"{jax.__version__} ({jax.default_backend()}), os.cpu_count() = {os.cpu_count()} "
        f"({len(os.sched_getaffinity(0))} in this process's affinity), "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    if args.only != "ensembles":
        fixture_figures(args)
    if args.only != "fixtures":
        ensemble_section(args)


def fixture_figures(args):
    """Sections 1-3: time per step, iterations, error and first-call time per fixture, and
    every configuration against the default."""
    ho = problems.harmonic_oscillator(dtype=jnp.float64)
    dp = problems.double_pendulum(dtype=jnp.float64)
    fixtures = [
        ("harmonic oscillator, GL8", ho, 8, args.ho_steps),
        ("double pendulum, GL16", dp, 16, min(DP_COMPARE_STEPS, args.dp_steps)),
    ]
    if args.dp_steps > DP_COMPARE_STEPS:
        fixtures.append(("double pendulum, GL16", dp, 16, args.dp_steps))
    groups = []
    for name, problem, nodes, steps in fixtures:
        rows = {c: fixture_run(problem, nodes, steps, args.repeats, c) for c in CONFIGS}
        groups.append((name, steps, rows))
    print(
        "\n| fixture (tanh width 10, h = 0.1) | steps | configuration | formulation | ok "
        "| t reached | us/step (median) | compile s | iters median | iters mean "
        "| rel. error q(t end) |"
    )
    print("|" + "---|" * 11)
    for name, steps, rows in groups:
        for config, r in rows.items():
            error = f"{r['error']:.2e}" if r["error"] is not None else "(failed)"
            print(
                f"| {name} | {steps} | {config} | {LABELS[config]} | {r['ok']} "
                f"| {r['t_end']:.1f} | {r['us_step']:.0f} | {r['compile_s']:.1f} "
                f"| {r['it_median']} | {r['it_mean']:.2f} | {error} |"
            )
    print(
        "\nevery configuration against the default (same run; configuration / default; "
        "the default dominates where it is ok, no slower per step, needs no more iterations "
        "(median and mean) and ends no less accurate):"
    )
    print(
        "| fixture | steps | configuration | time per step | iters median | iters mean "
        "| error | compile | dominated by the default |"
    )
    print("|" + "---|" * 9)
    for name, steps, rows in groups:
        base = rows["default"]
        for config, r in rows.items():
            if config == "default":
                continue
            if not r["ok"]:
                verdict = "yes" if base["ok"] else "no (both fail)"
                print(
                    f"| {name} | {steps} | {config} | {r['us_step'] / base['us_step']:.2f}x "
                    f"| {r['it_median'] / base['it_median']:.2f}x "
                    f"| {r['it_mean'] / base['it_mean']:.2f}x | fails at t = {r['t_end']:.1f} "
                    f"| {r['compile_s'] / base['compile_s']:.2f}x | {verdict} |"
                )
                continue
            error = (
                f"{r['error'] / base['error']:.3g}x" if base["error"] else "(default failed)"
            )
            dominated = base["ok"] and all(
                base[key] <= r[key] for key in ("us_step", "it_median", "it_mean", "error")
            )
            print(
                f"| {name} | {steps} | {config} | {r['us_step'] / base['us_step']:.2f}x "
                f"| {r['it_median'] / base['it_median']:.2f}x "
                f"| {r['it_mean'] / base['it_mean']:.2f}x | {error} "
                f"| {r['compile_s'] / base['compile_s']:.2f}x | {'yes' if dominated else 'no'} |"
            )
    defaults = [(name, steps, rows["default"]) for name, steps, rows in groups]
    ho_us = defaults[0][2]["us_step"]
    dp_us = max(r["us_step"] for name, _, r in defaults[1:])
    compile_s = max(r["compile_s"] for _, _, r in defaults)
    it_median = max(r["it_median"] for _, _, r in defaults)
    print(
        "targets (issue 27, the default): HO <= 150 us per step "
        f"({ho_us:.0f}: {'met' if ho_us <= 150 else 'NOT met'}), DP (GL16) <= 600 us per step "
        f"({dp_us:.0f}: {'met' if dp_us <= 600 else 'NOT met'}), first-call compile <= 6 s "
        f"(at most {compile_s:.1f}: {'met' if compile_s <= 6 else 'NOT met'}), median "
        f"iterations <= 3 (at most {it_median}: {'met' if it_median <= 3 else 'NOT met'})"
    )


def ensemble_section(args):
    """Sections 4-6: ensembles against a loop, the linear-solve floor, the sharded run."""
    timer = floor_timer(args.members)  # compiled once, for both uses
    per_loop, rows = ensemble_figures(
        args.members, args.vmap_members, args.loop_sample, args.repeats, floor=timer[0]
    )
    per_solve, iterations, n = linear_solve_floor(args.members, args.repeats, timer)
    floor = per_solve * iterations
    bound = per_loop / floor
    print(
        f"\nensembles of oscillator solves (10 steps each, the default solver: "
        f"VariableProjection, RoundoffNewton); Python loop of single jitted solves: "
        f"{per_loop * 1e3:.3f} ms per solve (median over {args.loop_sample} solves, "
        f"{args.repeats} repeats)"
    )
    print("| batch_size | members | ok | time ms (median) | us per member | compile s "
          "| throughput / loop | fraction of the floor's bound "
          "| max abs q difference from single solves |")
    print("|---|---|---|---|---|---|---|---|---|")
    for e in rows:
        print(
            f"| {e['mode']!r} | {e['members']} | {e['ok']} | {e['ens_s'] * 1e3:.1f} "
            f"| {e['ens_s'] / e['members'] * 1e6:.0f} | {e['ens_compile_s']:.1f} "
            f"| {e['speedup']:.2f}x | {e['floor_fraction']:.1%} | {e['diff']:.1e} |"
        )
    print(
        f"floor: the LU solve of the {n}x{n} reduced Jacobian of one Newton iteration "
        f"(jnp.linalg.solve), vmapped over {args.members} members, takes "
        f"{per_solve * 1e6:.2f} us per member; a member's solve takes {iterations} "
        f"iterations, so at least {floor * 1e6:.1f} us per member from the linear solves "
        f"alone: any ensemble is at most {bound:.0f}x the loop's throughput on this machine"
    )
    print(
        "targets: issue 7, throughput >= 50x a Python loop (met on a GPU); issue 27 on a "
        "CPU, throughput >= 80 % of the floor's bound"
    )
    if args.devices:
        cmd = module_command("benchmarks.speed", "--sharded-child", "--members",
                             str(args.members), "--repeats", str(args.repeats))
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        line = [s for s in proc.stdout.splitlines() if s.startswith("SHARDED")]
        if proc.returncode or not line:
            print(f"sharded run failed:\n{proc.stdout}\n{proc.stderr[-2000:]}")
        else:
            t_sh, t_un, diff, ndev, ok = line[0].split()[1:]
            print(
                f"sharded over {ndev} virtual CPU devices (one process, "
                f"{os.cpu_count()} cores): ok={ok}, {float(t_sh) * 1e3:.1f} ms vs unsharded "
                f"{float(t_un) * 1e3:.1f} ms in the same process "
                f"({float(t_un) / float(t_sh):.2f}x); max |sharded - unsharded| = "
                f"{float(diff):.1e}; this process's unsharded run (default batch_size, one "
                f"device): {rows[0]['ens_s'] * 1e3:.1f} ms"
            )


if __name__ == "__main__":
    main()
