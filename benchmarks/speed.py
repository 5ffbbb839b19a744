"""Every speed figure of the performance issue in one run: medians of repeats and ratios.

1. Time per step of `NetworkVI(ShallowNetBasis(tanh, 10), GaussLegendre(8))` on the harmonic
   oscillator (float64, h = 0.1, `--ho-steps` steps, default 1000), with the error of q at
   the end relative to the amplitude, and the median nonlinear iterations per step;
2. the same for the double pendulum with `GaussLegendre(16)` (`--dp-steps`, default 20);
   each in five configurations side by side (`CONFIGS`: the defaults, the Jacobian by
   `jax.jacrev`, the Jacobian in closed form (`jacobian="auto"`), the fast
   configuration: refitted neurons as seeds, the closed-form Jacobian and a solve ended by
   the first settled exact iteration, and `early-stop`: that stopping rule and Jacobian with
   the default seed);
3. first-call time (trace + compile + one run) minus one steady-state run of a ShallowNet
   `diffeqsolve`, per fixture;
4. ensembles of oscillator trajectories (10 steps each, random amplitudes) through
   `dvi.ensemble` against a Python loop of single jitted solves (timed on `--loop-sample`
   members, its throughput extrapolated): `--members` (default 1024) with the default
   `batch_size="auto"` (a compiled loop over members on a CPU) and `--vmap-members` (default
   128) with `batch_size=None` (full vmap, lockstep);
5. the floor of that ensemble on this machine: the linear solve of one Levenberg–Marquardt
   iteration (`damped_least_squares` of the member's square Jacobian), vmapped over
   `--members` members, per member, times the iterations of a member's solve: a lower bound
   on a member's time that ignores everything else a step does (Jacobian, residuals, seed
   fits), and so an upper bound on any ensemble's throughput against the loop;
6. with `--devices 8` (default), the same ensemble sharded over 8 virtual CPU devices in a
   subprocess (`XLA_FLAGS=--xla_force_host_platform_device_count=8`), its time and the
   largest difference from the unsharded result.

    PYTHONPATH=. .venv/bin/python benchmarks/speed.py [--quick] [--only fixtures|ensembles]

`--only fixtures` runs sections 1-3, `--only ensembles` sections 4-6.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import shlex
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
from jax.flatten_util import ravel_pytree  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import iteration_summary, timed  # noqa: E402
from diffrax_vi.linalg import damped_least_squares  # noqa: E402

H = 0.1


# The configurations compared: the defaults (the reference's seed on every step, a fresh
# Jacobian on every iteration, a stalled residual for 3 iterations before settled outputs end
# a solve), the Jacobian by reverse mode, the Jacobian assembled in closed form, and the fast
# one: the previous step's neurons refitted as seed, the closed-form Jacobian, and a solve
# ended by the first exact iteration whose outputs moved by at most eps^(3/4). (Reusing the
# Jacobian, `reuse_jacobian=3`, no longer pays once it is assembled in closed form: double
# pendulum 2.88 against 2.84 ms per step, oscillator 0.35 against 0.30 ms.)
CONFIGS = {
    "default": dict(),
    "jacrev": dict(root_finder=dvi.LevenbergMarquardt(jacobian="rev")),
    "auto": dict(root_finder=dvi.LevenbergMarquardt(jacobian="auto")),
    "fast": dict(
        reuse_neurons=True,
        root_finder=dvi.LevenbergMarquardt(jacobian="auto", settle=0, otol=2.0**-39),
    ),
    # the fast configuration's stopping rule and Jacobian with the default seed (the OGA fit
    # on every step): what the iteration count is with the default seed strategy
    "early-stop": dict(
        root_finder=dvi.LevenbergMarquardt(jacobian="auto", settle=0, otol=2.0**-39),
    ),
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
    t_end = float(sol.ts[-1])
    amplitude = float(np.max(np.abs(problem.reference(problem.ts)[0])))
    q_ref = problem.reference(np.array([t_end]))[0][0]
    error = float(np.max(np.abs(np.asarray(sol.ys[0][-1]) - q_ref))) / amplitude
    its = iteration_summary(sol.solver_state)
    return dict(
        ok=ok,
        ms_step=1e3 * total / max(its["steps"], 1),
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
_SOLVER = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8), **CONFIGS["fast"])


def solve_member(y0):
    sol = diffrax.diffeqsolve(
        _HO.term, _SOLVER, 0.0, 1.0, H, y0, saveat=diffrax.SaveAt(t1=True), throw=False
    )
    return sol.ys, sol.result == diffrax.RESULTS.successful


def ensemble_figures(members, vmap_members, loop_sample, repeats):
    """Throughput of `dvi.ensemble` (members per second) against a Python loop of single
    jitted solves: the default `batch_size` ("auto": one member after another on a CPU) on
    `members` members, and full `vmap` (`batch_size=None`, lockstep) on `vmap_members`."""
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
    rows = {}
    for mode, n in (("auto", members), (None, vmap_members)):
        y = (y0[0][:n], y0[1][:n])
        run = functools.partial(dvi.ensemble, solve_member, batch_size=mode)
        out, first = timed(run, y)
        t_ens = statistics.median(timed(run, y)[1] for _ in range(repeats))
        # every member against its own single solve (the first loop_sample of them)
        (q, _), ok = out
        diff = max(
            float(np.max(np.abs(np.asarray(q[i]) - np.asarray(single((y[0][i], y[1][i]))[0][0]))))
            for i in range(min(loop_sample, n))
        )
        rows[mode] = dict(
            members=n,
            ok=bool(np.all(np.asarray(ok))),
            ens_s=t_ens,
            ens_compile_s=first - t_ens,
            speedup=per_loop * n / t_ens,
            diff=diff,
        )
    return per_loop, rows


def least_squares_floor(members, repeats):
    """Seconds per member of the linear solve of one LM iteration, vmapped over `members`
    members of the ensemble's size, and the nonlinear iterations of one member's solve."""
    y0 = ensemble_inputs(1)
    sol = diffrax.diffeqsolve(
        _HO.term, _SOLVER, 0.0, 1.0, H, (y0[0][0], y0[1][0]),
        saveat=diffrax.SaveAt(t1=True, solver_state=True),
    )
    state = sol.solver_state
    n = ravel_pytree(state.theta)[0].size + y0[0].shape[1]  # network parameters and p_{n+1}
    rng = np.random.default_rng(1)
    jac = jnp.asarray(rng.standard_normal((members, n, n)))
    rhs = jnp.asarray(rng.standard_normal((members, n)))
    solve = jax.jit(jax.vmap(lambda a, b: damped_least_squares(a, b, 1e-4)))
    jax.block_until_ready(solve(jac, rhs))
    per_member = statistics.median(timed(solve, jac, rhs)[1] for _ in range(5 * repeats)) / members
    return per_member, int(state.iterations), n


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
    # 20 steps (t <= 2): at h = 0.1 the double pendulum's step [2.5, 2.6] has no root that the
    # solve reaches from any seed tried (OGA, refit, Hermite, other dictionaries and
    # dampings), and every configuration fails by t = 3.5; h = 0.05 runs to t = 10.
    parser.add_argument("--dp-steps", type=int, default=20)
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

    print(f"command: python {shlex.join(sys.argv)}")
    print(
        f"machine: {platform.platform()}, python {platform.python_version()}, jax "
        f"{jax.__version__} ({jax.default_backend()}), os.cpu_count() = {os.cpu_count()}, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    if args.only != "ensembles":
        fixture_figures(args)
    if args.only != "fixtures":
        ensemble_section(args)


def fixture_figures(args):
    """Sections 1-3: time per step, iterations, error and first-call time per fixture."""
    ho = problems.harmonic_oscillator(dtype=jnp.float64)
    dp = problems.double_pendulum(dtype=jnp.float64)
    rows = []
    for name, problem, nodes, steps in (
        ("harmonic oscillator, GL8", ho, 8, args.ho_steps),
        ("double pendulum, GL16", dp, 16, args.dp_steps),
    ):
        for config in CONFIGS:
            r = fixture_run(problem, nodes, steps, args.repeats, config)
            rows.append((name, steps, config, r))
    print(
        "\n| fixture (tanh width 10, h = 0.1) | steps | configuration | ok | ms/step (median) "
        "| compile s | iters median | iters mean | rel. error q(t end) |"
    )
    print("|" + "---|" * 9)
    for name, steps, jac, r in rows:
        print(
            f"| {name} | {steps} | {jac} | {r['ok']} | {r['ms_step']:.3f} | {r['compile_s']:.1f} "
            f"| {r['it_median']} | {r['it_mean']:.2f} | {r['error']:.2e} |"
        )
    print("\nratios against the defaults (same run):")
    n = len(CONFIGS)
    for i in range(0, len(rows), n):
        base = rows[i][3]
        for name, _, config, r in rows[i + 1 : i + n]:
            print(
                f"- {name}, {config}: time per step {r['ms_step'] / base['ms_step']:.2f}x, "
                f"compile {r['compile_s'] / base['compile_s']:.2f}x"
            )
    print("targets: HO <= 1 ms/step, DP <= 3 ms/step, median iterations <= 4, compile <= 10 s")


def ensemble_section(args):
    """Sections 4-6: ensembles against a loop, the linear-solve floor, the sharded run."""
    per_loop, rows = ensemble_figures(
        args.members, args.vmap_members, args.loop_sample, args.repeats
    )
    print(
        f"\nensembles of oscillator solves (10 steps each, fast configuration); Python loop of "
        f"single jitted solves: {per_loop * 1e3:.2f} ms per solve (median over "
        f"{args.loop_sample} solves, {args.repeats} repeats)"
    )
    print("| batch_size | members | ok | time ms (median) | compile s | throughput / loop "
          "| max abs q difference from single solves |")
    print("|---|---|---|---|---|---|---|")
    for mode, e in rows.items():
        print(
            f"| {mode!r} | {e['members']} | {e['ok']} | {e['ens_s'] * 1e3:.1f} | "
            f"{e['ens_compile_s']:.1f} | {e['speedup']:.2f}x | {e['diff']:.1e} |"
        )
    print("target (issue 7): throughput >= 50x a Python loop")
    per_solve, iterations, n = least_squares_floor(args.members, args.repeats)
    floor = per_solve * iterations
    print(
        f"floor: the {n}x{n} damped least-squares solve of one LM iteration, vmapped over "
        f"{args.members} members, takes {per_solve * 1e6:.1f} us per member; a member's "
        f"solve takes {iterations} iterations, so at least {floor * 1e3:.3f} ms per member "
        f"from the linear solves alone: any ensemble is at most {per_loop / floor:.1f}x the "
        f"loop's throughput on this machine"
    )
    if args.devices:
        cmd = [
            sys.executable,
            os.path.abspath(__file__),
            "--sharded-child",
            "--members",
            str(args.members),
            "--repeats",
            str(args.repeats),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True)
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
                f"{float(diff):.1e}"
            )


if __name__ == "__main__":
    main()
