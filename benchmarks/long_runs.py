"""How far one `diffeqsolve` of NetworkVI (tanh network, Gauss–Legendre nodes) gets on a
problem, and what it costs: steps done, failure report, relative energy error over 1001 saved
times (largest per tenth of the span, to tell a bounded error from a drift), wall time of the
first call (compile + run) and, with `--again`, of a second call.

Configurations: `fast` (refitted neurons, closed-form Jacobian, settle=0), `guarded`
(`fast`, refitting only after steps solved in at most 12 iterations), `default`
(all-parameter, `jacobian="auto"`), `fwd` (all-parameter, otherwise the defaults),
`projected` (the solver's defaults: the projected step) and `long-run` (refits
only from steps accepted at a residual of at most 2048·eps, closed-form Jacobian: the energy
study's long-run settings). `--retry` steps with `diffrax_vi.RetryFailedSteps()` instead of
`ConstantStepSize()`: a failed step is split into smaller pieces instead of ending the run.
`--peers tsit5:1e-10 dopri8:1e-12` adds adaptive diffrax runs over the same span (as in
`energy_drift.py`). `MAXIT=200` in the environment raises `root_find_max_steps`;
`--no-restart` sets `restart_failed=False`.

    .venv/bin/python -m benchmarks.long_runs double_pendulum 0.05 20000 10 16 fast
    .venv/bin/python -m benchmarks.long_runs double_pendulum 0.05 100000 10 8 \
        default --retry --peers tsit5:1e-10 dopri8:1e-12
    .venv/bin/python -m benchmarks.long_runs toda_lattice 0.1 20 8 16 fast --again

`--chunks K` runs the span as K consecutive solves, each starting from the previous one's
state and solver state (`diffeqsolve(..., solver_state=...)`), so the run is the same
sequence of steps as one solve; it prints a progress line per chunk. With `--checkpoint
FILE` the state after every chunk is written to FILE (`.npz`) and a later call with the same
arguments carries on from there: a run of hours survives an interruption. `--chunks-now M`
runs at most M chunks in this call (0: only report what the checkpoint holds).

    .venv/bin/python -m benchmarks.long_runs toda_lattice 0.1 100000 8 16 guarded \
        --chunks 50 --checkpoint benchmarks/results/long_runs/toda1e5_guarded.npz \
        --peers tsit5:1e-10 dopri8:1e-10 dopri8:1e-12
"""

from __future__ import annotations

import dataclasses
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.common import parse_peer, report_peers, span_parser  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench.harness import retry_step_budget  # noqa: E402

EPS = float(jnp.finfo(jnp.float64).eps)
FAST = dict(seed=dvi.SeedPolicy(reuse_neurons=True),
            root_finder=dvi.LevenbergMarquardt(jacobian="auto", settle=0, otol=2.0**-39))
CONFIGS = {"fast": FAST,
           "guarded": dict(FAST, seed=dvi.SeedPolicy(reuse_neurons=True, refit_iterations=12)),
           "default": dict(root_finder=dvi.LevenbergMarquardt(jacobian="auto")),
           "fwd": dict(formulation=dvi.FreeEndpoints()),
           "projected": {},
           "long-run": dict(seed=dvi.SeedPolicy(reuse_neurons=True, refit_residual=2048 * EPS),
                            root_finder=dvi.LevenbergMarquardt(jacobian="auto"))}


def per_tenth(ts: np.ndarray, error: np.ndarray, t0: float, t1: float) -> list[float]:
    """The largest error among the saved times in each tenth of [t0, t1] (NaN where none)."""
    edges = np.linspace(t0, t1, 11)
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        inside = error[(ts > a) & (ts <= b)]
        out.append(float(inside.max()) if inside.size else float("nan"))
    return out


def _checkpoint_label(label: dict) -> str:
    """What identifies a run for `--checkpoint`: every argument that changes its steps, and
    the solver options its configuration names (so that editing a configuration is noticed)."""
    keep = {k: v for k, v in label.items() if k not in ("peers", "checkpoint")}
    options = repr(sorted(CONFIGS[label["config"]].items()))
    return f"{sorted(keep.items())!r} {options} MAXIT={os.environ.get('MAXIT')}"


def chunked_run(problem, solver, controller, h: float, n: int, chunks: int, retry: bool,
                checkpoint: str | None, label: dict, at_most: int | None = None):
    """`n` steps of `h` as `chunks` consecutive solves, each handed the previous one's state,
    solver state and controller state. Saves 1000 / `chunks` evenly spaced times per chunk
    (1001 with the start); with `at_most`, stops after that many chunks in this call (resume
    from `checkpoint`). Returns (times, saved states, success, solver state, seconds,
    rejected step trials)."""
    per_chunk, saves = n // chunks, 1000 // chunks
    max_steps = retry_step_budget(per_chunk) if retry else per_chunk + 10

    @eqx.filter_jit
    def run_chunk(t_start, y0, solver_state, controller_state):
        t_end = t_start + per_chunk * h
        ts = t_start + (t_end - t_start) * jnp.arange(1, saves + 1) / saves
        ts = ts.at[-1].set(t_end)
        return diffrax.diffeqsolve(
            problem.term, solver, t_start, t_end, h, y0, args=problem.args,
            stepsize_controller=controller,
            saveat=diffrax.SaveAt(ts=ts, solver_state=True, controller_state=True),
            solver_state=solver_state, controller_state=controller_state, made_jump=False,
            throw=False, max_steps=max_steps)

    # The first chunk is handed initial states too, so that every chunk runs one program.
    t0 = jnp.asarray(problem.t0, jnp.float64)
    states = (solver.init(problem.term, t0, t0 + h, problem.y0, problem.args),
              controller.init(problem.term, t0, t0 + per_chunk * h, problem.y0, h,
                              problem.args, solver.func, solver.error_order(problem.term))[1])
    template = eqx.filter_eval_shape(run_chunk, t0, problem.y0, *states)
    kinds = (template.ys, template.solver_state, template.controller_state)
    tag = _checkpoint_label(label)
    ys = jax.tree_util.tree_map(lambda a: np.asarray(a)[None], problem.y0)
    seconds, done, ok, rejected = [], 0, True, 0
    if checkpoint is not None and os.path.exists(checkpoint):
        with np.load(checkpoint, allow_pickle=False) as saved:
            if str(saved["label"]) != tag:
                raise SystemExit(f"{checkpoint} was written by a different run:\n  "
                                 f"{saved['label']}\nthis run:\n  {tag}")
            done, ok, seconds = int(saved["done"]), bool(saved["ok"]), list(saved["seconds"])
            rejected = int(saved["rejected"])
            parts = []
            for name, kind in zip(("ys", "solver", "controller"), kinds, strict=True):
                leaves, treedef = jax.tree_util.tree_flatten(kind)
                parts.append(jax.tree_util.tree_unflatten(
                    treedef, [saved[f"{name}_{i}"] for i in range(len(leaves))]))
            ys, states = parts[0], (parts[1], parts[2])
        print(f"resuming from {checkpoint}: {done} of {chunks} chunks done", flush=True)
    stop = chunks if at_most is None else min(chunks, done + at_most)
    while done < stop and ok:
        t_start = problem.t0 + done * per_chunk * h
        y0 = jax.tree_util.tree_map(lambda a: jnp.asarray(a[-1]), ys)
        begin = time.perf_counter()
        sol = jax.block_until_ready(
            run_chunk(jnp.asarray(t_start, jnp.float64), y0, *states))
        seconds.append(time.perf_counter() - begin)
        ok = bool(sol.result == diffrax.RESULTS.successful)
        rejected += int(sol.stats["num_rejected_steps"])
        ys = jax.tree_util.tree_map(lambda a, b: np.concatenate([a, np.asarray(b)]), ys,
                                    sol.ys)
        before = states[0]
        states = (sol.solver_state, sol.controller_state)
        done += 1
        steps = int(sol.solver_state.steps) - int(before.steps)
        iterations = int(sol.solver_state.iterations) - int(before.iterations)
        carried = sum(int(getattr(sol.solver_state, k)) - int(getattr(before, k))
                      for k in ("refits", "warm_starts"))
        fresh = steps - carried
        print(f"chunk {done}/{chunks}: t = {t_start + per_chunk * h:.6g}, ok {ok}, steps "
              f"done {int(sol.solver_state.steps)}, {seconds[-1]:.1f} s, mean iterations "
              f"{iterations / max(steps, 1):.2f}, seeded by a fresh fit {fresh}", flush=True)
        if not ok:
            print(dvi.describe_failure(sol), flush=True)
        if checkpoint is not None:
            arrays = {"label": np.asarray(tag), "done": np.asarray(done),
                      "ok": np.asarray(ok), "seconds": np.asarray(seconds),
                      "rejected": np.asarray(rejected)}
            for name, tree in zip(("ys", "solver", "controller"), (ys, *states), strict=True):
                for i, leaf in enumerate(jax.tree_util.tree_leaves(tree)):
                    arrays[f"{name}_{i}"] = np.asarray(leaf)
            tmp = checkpoint + ".tmp.npz"
            np.savez(tmp, **arrays)
            os.replace(tmp, checkpoint)
    saved_times = jax.tree_util.tree_leaves(ys)[0].shape[0]
    ts = problem.t0 + np.arange(saved_times) * (n * h / 1000)
    total = float(np.sum(seconds))
    if done < chunks and ok:
        print(f"stopped after {done} of {chunks} chunks; the same command carries on",
              flush=True)
    if seconds:
        print(f"{done} chunks in {total:.0f} s, median chunk {np.median(seconds):.1f} s "
              f"(each call's first chunk includes compiling)", flush=True)
    return ts, ys, ok, states[0], total, rejected


def main(argv=None):
    parser = span_parser(__doc__)
    parser.add_argument("width", type=int)
    parser.add_argument("nodes", type=int)
    parser.add_argument("config", choices=sorted(CONFIGS))
    parser.add_argument("--again", action="store_true", help="time a second call")
    parser.add_argument("--no-restart", action="store_true", help="restart_failed=False")
    parser.add_argument("--chunks", type=int, default=None,
                        help="run the span as this many consecutive solves (a divisor of "
                             "both the number of steps and 1000)")
    parser.add_argument("--chunks-now", type=int, default=None,
                        help="with --checkpoint: run at most this many chunks in this call "
                             "(0: report what the checkpoint holds)")
    parser.add_argument("--checkpoint", default=None,
                        help="with --chunks: .npz file to save to after every chunk and to "
                             "resume from")
    parser.add_argument("--retry", action="store_true",
                        help="step with RetryFailedSteps() instead of ConstantStepSize()")
    ns = parser.parse_args(argv)
    peers = [parse_peer(parser, text) for text in ns.peers]
    if ns.chunks is not None and (ns.chunks < 1 or ns.steps % ns.chunks or 1000 % ns.chunks):
        parser.error(f"--chunks {ns.chunks} must divide both the number of steps "
                     f"({ns.steps}) and the 1000 saved intervals")
    if ns.checkpoint is not None and ns.chunks is None:
        parser.error("--checkpoint needs --chunks")
    if ns.chunks_now is not None and (ns.checkpoint is None or ns.chunks_now < 0):
        parser.error("--chunks-now needs --checkpoint and a count >= 0")
    if ns.again and ns.chunks is not None:
        parser.error("--again times one solve; it does not combine with --chunks")
    problem = getattr(problems, ns.problem)(dtype=jnp.float64)
    kw = dict(CONFIGS[ns.config])
    if os.environ.get("MAXIT"):
        kw["root_find_max_steps"] = int(os.environ["MAXIT"])
    if ns.no_restart:
        kw["seed"] = dataclasses.replace(kw.get("seed", dvi.SeedPolicy()), restart_failed=False)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, ns.width),
                           dvi.GaussLegendre(ns.nodes), **kw)
    h, n = ns.h, ns.steps
    t1 = problem.t0 + n * h
    controller = dvi.RetryFailedSteps() if ns.retry else diffrax.ConstantStepSize()
    if ns.chunks is not None:
        ts, ys, ok, state, first, rejected = chunked_run(
            problem, solver, controller, h, n, ns.chunks, ns.retry, ns.checkpoint,
            label={k: v for k, v in vars(ns).items() if k != "chunks_now"},
            at_most=ns.chunks_now)
    else:
        ts = jnp.linspace(problem.t0, t1, 1001)
        max_steps = retry_step_budget(n) if ns.retry else n + 10

        @eqx.filter_jit
        def run(y0):
            return diffrax.diffeqsolve(
                problem.term, solver, problem.t0, t1, h, y0, args=problem.args,
                stepsize_controller=controller,
                saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False,
                max_steps=max_steps)

        start = time.perf_counter()
        sol = jax.block_until_ready(run(problem.y0))
        first = time.perf_counter() - start
        state = sol.solver_state
        if ns.again:
            start = time.perf_counter()
            sol = jax.block_until_ready(run(problem.y0))
            again = time.perf_counter() - start
            print(f"first call {first:.1f} s, second {again:.2f} s = "
                  f"{1e3 * again / int(state.steps):.1f} ms/step, mean iterations "
                  f"{int(state.iterations) / int(state.steps):.2f}")
        ys, ok = sol.ys, bool(sol.result == diffrax.RESULTS.successful)
        rejected = int(sol.stats["num_rejected_steps"])
    steps = int(state.steps)
    q, p = (np.asarray(a) for a in ys)
    finite = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(p), axis=1)
    e0 = float(problem.energy(problem.t0, *problem.y0))
    energy = np.asarray(jax.vmap(lambda a, b: problem.energy(problem.t0, a, b))(
        jnp.asarray(q[finite]), jnp.asarray(p[finite])))
    error = np.abs(energy - e0) / abs(e0)
    retry = f", failed trials retried in pieces {rejected}" if ns.retry else ""
    print(f"{ns.problem} h {h} steps {n} width {ns.width} nodes {ns.nodes} {ns.config}: "
          f"ok {ok}, steps done {steps}{retry}, restarts {int(state.restarts)}, "
          f"{'wall time' if ns.chunks else 'first call'} {first:.1f} s, "
          f"max relative energy error {error.max():.2e}")
    if ns.chunks is not None:
        print(f"  mean iterations per step {int(state.iterations) / max(steps, 1):.2f}")
    tenths = per_tenth(np.asarray(ts)[finite], error, problem.t0, t1)
    print("  largest energy error per tenth of the span: "
          + " ".join(f"{w:.1e}" for w in tenths))
    if not ok and ns.chunks is None:
        print(dvi.describe_failure(sol))
    report_peers(peers, problem, h, n, prefix="")


if __name__ == "__main__":
    main()
