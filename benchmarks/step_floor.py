"""How far the variational step is from the hardware's floor, side by side in one process.

Kepler (e = 0.5, float64), time per step of a whole jitted `diffeqsolve` with constant
steps, alone and per member-step of a `vmap` over `--members` orbits (e in [0.1, 0.6]):

- `CGVI(k)` by default: the Jacobian-free iteration (`diffrax_vi._step.jacobian_free`) on this
  constant-mass Lagrangian;
- the same with `picard=False`: the chord iteration with the Jacobian formed once per step;
- the default projected `NetworkVI` (tanh, `k + 1` neurons, Gauss–Legendre `k + 1`: the
  same span dimension; the same engine), with `ChordIteration(picard=True)`, and with
  `RoundoffNewton` without the engine;
- `diffrax.Dopri8` at `--dopri-rtol`;
- the floor: a plain-JAX Gauss collocation step with `k + 1` stages, a fixed count of
  fixed-point updates (`--floor-updates`) and `lax.scan` over the steps (cost only: its
  error is not comparable).

Each row also counts the kernels one step launches (`kernels_per_run`: XLA's CPU runtime
runs a compiled program as a sequence of kernels, each with a fixed cost of its own; the count
is read from a profile of one run and does not depend on the machine's load).

Then the size of the program of a 10-step solve (`program_sizes`: jaxpr equations,
optimised HLO instructions, while loops), and the first call of a fresh process (trace,
compile and one run; no persistent compilation cache) of `CGVI(6)` (its default, and the
chord iteration with its restart, the default before 2026-12-02) and `NetworkVI` against
`diffrax.Dopri8`'s on the same problem, double pendulum and Kepler, 10 steps each: `--fresh`
runs, interleaved, medians and their ratios. Beside them, as a calibration of what an
implicit step costs to compile, diffrax's own implicit solvers `Kvaerno5` and `ImplicitEuler`
(`VeryChord` at rtol = atol = 1e-12; their results are not used: at this step `Kvaerno5`'s
Newton solve diverges on the double pendulum).

    .venv/bin/python -m benchmarks.step_floor [--degree 6] [--members 256] [--fresh 5]
        [--only steps|sizes|first-call]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import time

import numpy as np


def _timed(fn, *args, repeats: int) -> float:
    """Best wall time of `repeats` calls after one warm-up (seconds)."""
    import jax

    jax.block_until_ready(fn(*args))
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return best


def kernels_per_run(fn, *args) -> tuple[int, int]:
    """`(kernels, executor calls)` of one run of the compiled `fn`, counted in a profile of
    the run: what XLA's CPU runtime launches (its thunks), a figure that load and timing
    noise do not change."""
    import glob
    import gzip
    import json
    import tempfile

    import jax

    jax.block_until_ready(fn(*args))
    with tempfile.TemporaryDirectory() as folder:
        jax.profiler.start_trace(folder, create_perfetto_trace=True)
        jax.block_until_ready(fn(*args))
        jax.profiler.stop_trace()
        (trace,) = glob.glob(folder + "/**/*.trace.json.gz", recursive=True)
        with gzip.open(trace) as f:
            events = json.load(f)["traceEvents"]
    names = [e["name"] for e in events if e.get("ph") == "X"]
    runtime = ("end:", "ThreadpoolListener", "ThunkExecutor", "$", "Pjit", "CommonPjRt",
               "PjRt")
    kernels = [n for n in names if not n.startswith(runtime) and "Execute" not in n]
    return len(kernels), sum(1 for n in names if n == "ThunkExecutor::Execute")


def kepler_states(eccentricities):
    import jax.numpy as jnp

    e = np.asarray(eccentricities, np.float64)
    q = jnp.asarray(np.stack([1 - e, 0 * e], -1))
    p = jnp.asarray(np.stack([0 * e, np.sqrt((1 + e) / (1 - e))], -1))
    return q, p


def gauss_floor(stages: int, h: float, updates: int):
    """A plain-JAX Gauss collocation step (first-order stages, fixed updates): cost only."""
    import jax.numpy as jnp
    from numpy.polynomial.legendre import leggauss

    x, w = leggauss(stages)
    c, b = (x + 1) / 2, w / 2
    a = np.zeros((stages, stages))
    for j in range(stages):
        poly = np.poly1d([1.0])
        for m in range(stages):
            if m != j:
                poly *= np.poly1d([1.0, -c[m]]) / (c[j] - c[m])
        integral = poly.integ()
        a[:, j] = integral(c) - integral(0)

    def acc(q):
        r2 = jnp.sum(q * q, -1, keepdims=True)
        return -q / (r2 * jnp.sqrt(r2))

    def combine(m, k):
        return jnp.sum(jnp.asarray(m)[None] * k.T[:, None, :], -1).T

    def step(y, _):
        q, p = y
        k = jnp.broadcast_to(acc(q), (stages, q.shape[-1]))
        for _ in range(updates):
            stage_p = p + h * combine(a, k)
            k = acc(q + h * combine(a, stage_p))
        stage_p = p + h * combine(a, k)
        return (q + h * (b @ stage_p), p + h * (b @ k)), None

    return step


def step_costs(args) -> list[str]:
    import diffrax
    import jax
    import jax.numpy as jnp

    import diffrax_vi as dvi
    from diffrax_vi.problems import kepler

    degree, h = args.degree, 2 * math.pi / args.steps_per_orbit
    orbits = args.orbits
    n = args.steps_per_orbit * orbits
    term = kepler(eccentricity=0.5).term
    fpi = dvi.ChordIteration(ftol=0.0, predict=True, picard=True)
    width = degree + 1
    solvers = {
        f"CGVI({degree}) default (engine)": dvi.CGVI(degree),
        f"CGVI({degree}) chord": dvi.CGVI(
            degree, root_finder=dvi.ChordIteration(ftol=0.0, predict=True, picard=False)
        ),
        f"NetworkVI(tanh {width}) default": dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(degree + 1)
        ),
        f"NetworkVI(tanh {width}) FPI engine": dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(degree + 1),
            root_finder=fpi,
        ),
        f"NetworkVI(tanh {width}) Newton": dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(degree + 1),
            root_finder=dvi.RoundoffNewton(confirm=False),
        ),
    }
    lines = [f"# Kepler e = 0.5, h = 2pi/{args.steps_per_orbit}, {orbits} orbits alone, "
             f"{args.ensemble_orbits} orbits x {args.members} members under vmap"]
    lines.append(f"{'solver':34s} {'us/step':>9s} {'us/member-step':>15s} {'error':>9s} "
                 f"{'updates/step':>12s} {'kernels/step':>12s}")
    q0, p0 = kepler_states([0.5])
    qs, ps = kepler_states(np.linspace(0.1, 0.6, args.members))
    m = args.steps_per_orbit * args.ensemble_orbits

    def diffrax_run(solver, steps, controller=None, dt0=h):
        def run(q, p):
            sol = diffrax.diffeqsolve(
                term, solver, 0.0, steps * h, dt0, (q, p), max_steps=steps * 4 + 16,
                saveat=diffrax.SaveAt(t1=True),
                stepsize_controller=controller or diffrax.ConstantStepSize(),
            )
            return sol.ys[0][-1], sol.stats["num_steps"]
        return run

    from diffrax_vi.problems import solve_kepler_equation

    anomaly = solve_kepler_equation(np.array([n * h]), 0.5)[0]
    q_exact = np.array([math.cos(anomaly) - 0.5, math.sqrt(0.75) * math.sin(anomaly)])
    rows = dict(solvers)
    rows["Dopri8"] = diffrax.Dopri8()
    for name, solver in rows.items():
        controller = None
        dt0 = h
        if name == "Dopri8":
            controller = diffrax.PIDController(rtol=args.dopri_rtol, atol=args.dopri_rtol)
            dt0 = None
        one = jax.jit(diffrax_run(solver, n, controller, dt0))
        seconds = _timed(one, q0[0], p0[0], repeats=args.repeats)
        q_end, steps = one(q0[0], p0[0])
        kernels, _ = kernels_per_run(one, q0[0], p0[0])
        error = float(np.max(np.abs(np.asarray(q_end) - q_exact)))
        many = jax.jit(jax.vmap(diffrax_run(solver, m, controller, dt0)))
        batch_seconds = _timed(many, qs, ps, repeats=max(1, args.repeats // 2))
        _, batch_steps = many(qs, ps)
        per_member = batch_seconds / (args.members * float(np.mean(np.asarray(batch_steps))))
        updates = "-"
        if name in solvers:  # the nonlinear updates per step, from the solver's state
            state = diffrax.diffeqsolve(
                term, solver, 0.0, n * h, h, (q0[0], p0[0]), max_steps=n,
                saveat=diffrax.SaveAt(t1=True, solver_state=True),
            ).solver_state
            updates = f"{float(state.iterations) / float(state.steps):.2f}"
        lines.append(f"{name:34s} {seconds / int(steps) * 1e6:9.2f} {per_member * 1e6:15.3f} "
                     f"{error:9.1e} {updates:>12s} {kernels / int(steps):12.1f}")
    floor = gauss_floor(degree + 1, h, args.floor_updates)
    one = jax.jit(lambda q, p: jax.lax.scan(floor, (q, p), None, length=n)[0])
    seconds = _timed(one, q0[0], p0[0], repeats=args.repeats)
    kernels, _ = kernels_per_run(one, q0[0], p0[0])
    many = jax.jit(jax.vmap(lambda q, p: jax.lax.scan(floor, (q, p), None, length=m)[0]))
    batch_seconds = _timed(many, qs, ps, repeats=max(1, args.repeats // 2))
    lines.append(f"{'floor: plain-JAX Gauss, ' + str(args.floor_updates) + ' updates':34s} "
                 f"{seconds / n * 1e6:9.2f} {batch_seconds / (args.members * m) * 1e6:15.3f} "
                 f"{'-':>9s} {'-':>12s} {kernels / n:12.1f}")
    del jnp
    return lines


def _equations(jaxpr) -> int:
    """Equations of a jaxpr, counting those of its sub-jaxprs (loops, branches, calls) in
    place of the equation that holds them."""
    from jax.extend.core import ClosedJaxpr, Jaxpr

    count = 0
    for eqn in jaxpr.eqns:
        inner = [p for v in eqn.params.values() for p in (v if isinstance(v, tuple | list)
                                                           else (v,))
                 if isinstance(p, ClosedJaxpr | Jaxpr)]
        count += sum(_equations(p.jaxpr if isinstance(p, ClosedJaxpr) else p)
                     for p in inner) if inner else 1
    return count


def program_sizes(args) -> list[str]:
    """The size of the program of a 10-step solve (what its first call traces and compiles):
    equations of its jaxpr, instructions and while loops of XLA's optimised HLO. Beside the
    default `CGVI(6)` (the Jacobian-free iteration where the kinetic matrix is constant):
    that with its Newton fallback compiled in, the chord iteration (the default where the
    kinetic matrix varies), and with the restart of a solve not converged in `FIRST_TRY`
    updates (`restart=True`, the default before 2026-12-02); the default `NetworkVI`, and
    with Newton's restart as its default had it."""
    import diffrax
    import jax

    import diffrax_vi as dvi
    from diffrax_vi import problems

    fallback = dvi.ChordIteration(ftol=0.0, predict=True, picard=True,
                                       picard_fallback=True)
    chord = dvi.ChordIteration(ftol=0.0, predict=True)
    restarting = dvi.ChordIteration(ftol=0.0, predict=True, restart=True)
    implicit = diffrax.VeryChord(rtol=1e-12, atol=1e-12)
    solvers = {
        "Dopri8": diffrax.Dopri8(),
        "Kvaerno5": diffrax.Kvaerno5(root_finder=implicit),
        "ImplicitEuler": diffrax.ImplicitEuler(root_finder=implicit),
        "CGVI(6)": dvi.CGVI(6),
        "CGVI(6) engine+fallback": dvi.CGVI(6, root_finder=fallback),
        "CGVI(6) chord": dvi.CGVI(6, root_finder=chord),
        "CGVI(6) chord+restart": dvi.CGVI(6, root_finder=restarting),
        "NetworkVI": dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10)),
        "NetworkVI Newton+restart": dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, 10),
            root_finder=dvi.RoundoffNewton(confirm=False, restart=True)),
    }
    lines = ["# program of a 10-step solve: jaxpr equations, optimised HLO instructions, "
             "while loops"]
    for name in ("double_pendulum", "kepler"):
        problem = getattr(problems, name)()
        h = float(problem.dt)
        for which, solver in solvers.items():
            def run(y0, solver=solver):
                return diffrax.diffeqsolve(problem.term, solver, 0.0, 10 * h, h, y0,
                                           args=problem.args, max_steps=16).ys
            equations = _equations(jax.make_jaxpr(run)(problem.y0).jaxpr)
            hlo = jax.jit(run).lower(problem.y0).compile().as_text()
            instructions = sum(" = " in line for line in hlo.splitlines())
            lines.append(f"{name:16s} {which:24s} jaxpr {equations:5d}  HLO {instructions:5d}  "
                         f"while {hlo.count(' while('):3d}")
    return lines


FIRST_CALL = """
import sys, time
start = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import diffrax, diffrax_vi as dvi
from diffrax_vi import problems
name, which = sys.argv[1], sys.argv[2]
problem = getattr(problems, name)()
restarting = dvi.ChordIteration(ftol=0.0, predict=True, restart=True)
implicit = diffrax.VeryChord(rtol=1e-12, atol=1e-12)
solver = {"Dopri8": diffrax.Dopri8(), "CGVI(6)": dvi.CGVI(6),
          "Kvaerno5": diffrax.Kvaerno5(root_finder=implicit),
          "ImplicitEuler": diffrax.ImplicitEuler(root_finder=implicit),
          "CGVI(6) chord+restart": dvi.CGVI(6, root_finder=restarting),
          "NetworkVI": dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10))}[which]
h = float(problem.dt)
t0 = time.perf_counter()
# diffrax's implicit solvers are timed for their compilation only (see the docstring)
sol = diffrax.diffeqsolve(problem.term, solver, 0.0, 10 * h, h, problem.y0, args=problem.args,
                          max_steps=16, throw=which in ("Dopri8", "CGVI(6)", "NetworkVI",
                                                        "CGVI(6) chord+restart"))
jax.block_until_ready(sol.ys)
print(time.perf_counter() - t0)
"""


def first_calls(args) -> list[str]:
    lines = [f"# first call in a fresh process (trace + compile + run, 10 steps), median of "
             f"{args.fresh} interleaved runs"]
    for problem in ("double_pendulum", "kepler"):
        times = {which: [] for which in ("Dopri8", "CGVI(6)", "CGVI(6) chord+restart",
                                         "NetworkVI", "Kvaerno5", "ImplicitEuler")}
        for _ in range(args.fresh):
            for which in times:
                out = subprocess.run(
                    [sys.executable, "-c", FIRST_CALL, problem, which], capture_output=True,
                    text=True, check=True,
                )
                times[which].append(float(out.stdout.strip().splitlines()[-1]))
        dopri = statistics.median(times["Dopri8"])
        for which, values in times.items():
            median = statistics.median(values)
            lines.append(f"{problem:16s} {which:22s} median {median:6.2f} s "
                         f"({', '.join(f'{v:.2f}' for v in values)}), "
                         f"{median / dopri:4.2f}x Dopri8")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--degree", type=int, default=6)
    parser.add_argument("--steps-per-orbit", type=int, default=64)
    parser.add_argument("--orbits", type=int, default=20)
    parser.add_argument("--ensemble-orbits", type=int, default=2)
    parser.add_argument("--members", type=int, default=256)
    parser.add_argument("--floor-updates", type=int, default=4)
    parser.add_argument("--dopri-rtol", type=float, default=1e-13)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--fresh", type=int, default=5, help="0 skips the first calls")
    parser.add_argument("--only", choices=("steps", "sizes", "first-call"))
    parser.add_argument(
        "--whole-loops", type=int, default=0, metavar="BYTES",
        help="let XLA's CPU backend compile a while loop whose one pass touches fewer than "
             "BYTES bytes as one function (xla_cpu_small_while_loop_byte_threshold; XLA's "
             "default is 1024): set in XLA_FLAGS before jax starts, for this process and "
             "the first calls' processes",
    )
    args = parser.parse_args()
    if args.whole_loops:
        # Merged into XLA_FLAGS (the first calls' processes inherit it), before jax starts.
        from diffrax_vi import compile_loops_whole

        compile_loops_whole(args.whole_loops)
    import jax

    jax.config.update("jax_enable_x64", True)
    print(f"# jax {jax.__version__} on {jax.devices()[0].platform}; "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    if args.only in (None, "steps"):
        print("\n".join(step_costs(args)), flush=True)
    if args.only in (None, "sizes"):
        print("\n".join(program_sizes(args)), flush=True)
    if args.only in (None, "first-call") and args.fresh:
        print("\n".join(first_calls(args)), flush=True)


if __name__ == "__main__":
    main()
