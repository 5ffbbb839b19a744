"""The structure of a converged NetworkVI step, measured by singular values (issue 27).

For the default free-endpoint, all-parameter step
`NetworkVI(ShallowNetBasis(act, width), GaussLegendre(nodes))` this solves `--steps` steps of
`diffrax.diffeqsolve` (float64, default 1) and, at the converged parameters of the last step
(`sol.solver_state.theta`, `(3S, D)` in the order α, w, β per coordinate), reports three
spectra. Ranks are counts of singular values above a fraction of the largest one.

(a) tangent data, per coordinate `d`: the Jacobian of the data map
    `θ_d ↦ (q_d(c_j), q_d'(c_j) for the R nodes, q_d(0), q_d(1))`, `(2R+2) × 3S`: the only
    numbers through which the quadrature-approximated action and the boundary terms see the
    curve. Rank at 1e-8 and 1e-13.
(b) the step Jacobian: `jax.jacfwd` of `FreeEndpoints.residual` in the unknowns
    `(θ, p_{n+1})` at the converged iterate, `(3S·D + D)` square, in the context the solver
    builds (`NetworkVI._context`). Rank at 1e-8 and 1e-13, and the largest singular value.
(c) the hidden-layer features with the output weights removed, per coordinate: rows
    `sqrt(b_j) σ(w_i c_j + β_i)`, `sqrt(b_j) w_i σ'(w_i c_j + β_i)` for the nodes, then
    `σ(β_i)` and `σ(w_i + β_i)`, `(2R+2) × S`: the span a variable-projection formulation
    would solve for the output weights in. Rank at 1e-8, 1e-11 and 1e-13 (full = S).

A combination the solver refuses at construction (too few nodes for the width) gets a
`refused` row; a step that does not converge a `failed` row (no spectra). For a problem with
several coordinates (double pendulum) the per-coordinate ranks are joined by `/`.
The HO step sizes share one compilation per (activation, width, nodes): `t1` and `dt0` are
traced.

    .venv/bin/python -m benchmarks.step_structure            # full grid
    .venv/bin/python -m benchmarks.step_structure --quick    # tanh, S 6/10, R 8/16
    .venv/bin/python -m benchmarks.step_structure --tiny --out -   # smoke test

Writes the table to `--out` (default `benchmarks/results/step_structure.txt`, or
`step_structure_quick.txt` with `--quick`; `-` prints only; `--append` adds to it) and prints
it as it goes. `--problems`, `--activations`, `--widths`, `--nodes` replace a part of the grid.
The committed table was cut down to fit a 2-core machine (about 10 s per compiled
combination): the oscillator on the whole grid, the double pendulum with tanh and GELU only:

    .venv/bin/python -m benchmarks.step_structure --problems ho0.1 ho0.5
    .venv/bin/python -m benchmarks.step_structure --problems dp0.1 \\
        --activations tanh gelu --append
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.common import command_line  # noqa: E402
from diffrax_vi import problems  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
ACTIVATIONS = {"tanh": dvi.tanh, "gelu": dvi.gelu, "sigmoid": dvi.sigmoid, "sin": dvi.sin}
# (label, problem factory, step size)
PROBLEMS = {
    "ho0.1": ("harmonic_oscillator", 0.1),
    "ho0.5": ("harmonic_oscillator", 0.5),
    "dp0.1": ("double_pendulum", 0.1),
}
GRID = dict(problems=list(PROBLEMS), activations=list(ACTIVATIONS),
            widths=[4, 6, 8, 10, 12, 16], nodes=[4, 8, 12, 16])
QUICK = dict(problems=["ho0.1"], activations=["tanh"], widths=[6, 10], nodes=[8, 16])
TINY = dict(problems=["ho0.1"], activations=["tanh"], widths=[6], nodes=[8])
RTOLS_AB = (1e-8, 1e-13)
RTOLS_C = (1e-8, 1e-11, 1e-13)


def rank(s: np.ndarray, rtol: float) -> int:
    """Singular values above `rtol` times the largest."""
    return int(np.sum(s > rtol * s[0])) if s.size and s[0] > 0 else 0


def _measure_fn(solver, problem, steps: int):
    """A compiled `dt0 -> (solution, matrices)`: `steps` steps from `problem.y0`, and at the
    converged parameters of the last one the tangent-data matrices `(D, 2R+2, 3S)`, the step
    Jacobian, the residual there and the feature matrices `(2R+2, S, D)`. The step size is
    traced, so step sizes share the compilation."""

    @eqx.filter_jit
    def run(dt0):
        t0 = problem.t0
        t_start = t0 + (steps - 1) * dt0
        sol = diffrax.diffeqsolve(
            problem.term, solver, t0, t0 + steps * dt0, dt0, problem.y0, args=problem.args,
            saveat=diffrax.SaveAt(ts=jnp.stack([t_start, t0 + steps * dt0]), solver_state=True),
            max_steps=steps + 1, throw=False,
        )
        theta = sol.solver_state.theta
        (q, p) = sol.ys
        return sol, _matrices(solver, problem, theta, (q[0], p[0]), p[1], t_start, dt0)

    return run


def _matrices(solver, problem, theta, y_start, p_end, t_start, dt):
    ctx = solver.step_context(problem.term, t_start, t_start + dt, y_start, problem.args)
    basis, form = ctx.basis, solver.formulation
    nodes, weights = ctx.nodes, ctx.weights
    taus = jnp.concatenate([nodes, jnp.array([0.0, 1.0], nodes.dtype)])
    n_nodes = nodes.shape[0]

    def data(theta_d):  # (2R+2,): values and slopes at the nodes, values at 0 and 1
        def curve(tau):
            return basis.evaluate(theta_d[:, None], tau)[0]

        q, dq = jax.vmap(lambda t: jax.jvp(curve, (t,), (jnp.ones_like(t),)))(taus)
        return jnp.concatenate([q[:n_nodes], dq[:n_nodes], q[n_nodes:]])

    tangent = jax.vmap(jax.jacfwd(data), in_axes=1)(theta)  # (D, 2R+2, 3S)
    flat, unravel = ravel_pytree((theta, p_end))

    def residual(u):
        return ravel_pytree(form.residual(unravel(u), ctx))[0]

    _, w, beta = basis.split(theta)  # each (S, D)
    act = solver.basis.activation
    root_b = jnp.sqrt(weights)[:, None, None]
    z = w[None] * nodes[:, None, None] + beta[None]  # (R, S, D)
    s0, s1 = jax.jvp(act, (z,), (jnp.ones_like(z),))
    features = jnp.concatenate([
        root_b * s0, root_b * w[None] * s1, act(beta)[None], act(w + beta)[None],
    ])  # (2R+2, S, D)
    return dict(tangent=tangent, jacobian=jax.jacfwd(residual)(flat),
                residual=jnp.max(jnp.abs(residual(flat))), features=features)


def _spectra(m) -> dict:
    """Singular values (a) per coordinate, (b), (c) per coordinate."""
    sv = np.linalg.svd
    features = np.asarray(m["features"])
    return dict(
        a=[sv(t, compute_uv=False) for t in np.asarray(m["tangent"])],
        b=sv(np.asarray(m["jacobian"]), compute_uv=False),
        c=[sv(features[:, :, d], compute_uv=False) for d in range(features.shape[2])],
        residual=float(m["residual"]),
    )


def _joined(values) -> str:
    return "/".join(str(v) for v in values)


HEADER = ("| problem | act | S | R | status | it | max abs F | "
          "(a) shape | (a) >1e-8 | (a) >1e-13 | (a) s_max | (a) s_min | "
          "(b) n | (b) >1e-8 | (b) >1e-13 | (b) s_max | "
          "(c) shape | (c) >1e-8 | (c) >1e-11 | (c) >1e-13 | (c) full@1e-11 |")


def measure(label, act_name, width, n_nodes, steps, cache) -> str:
    """One table row."""
    name, dt = PROBLEMS[label]
    head = f"| {label} | {act_name} | {width} | {n_nodes} |"
    empty = " – |" * 15  # the columns after `it`
    try:
        solver = dvi.NetworkVI(dvi.ShallowNetBasis(ACTIVATIONS[act_name], width),
                               dvi.GaussLegendre(n_nodes))
    except ValueError:
        return head + " refused | – |" + empty
    problem = getattr(problems, name)(dtype=jnp.float64)
    key = (name, act_name, width, n_nodes)
    if key not in cache:
        if cache:  # one compiled solve at a time: a long grid otherwise runs out of memory
            cache.clear()
            jax.clear_caches()
        cache[key] = _measure_fn(solver, problem, steps)
    sol, matrices = cache[key](jnp.asarray(dt, jnp.float64))
    state = sol.solver_state
    its = int(state.last_iterations)
    if sol.result != diffrax.RESULTS.successful:
        return head + f" failed | {its} |" + empty
    r = _spectra(matrices)
    rows_a, cols_a = 2 * n_nodes + 2, 3 * width
    a, b, c = r["a"], r["b"], r["c"]
    full = all(rank(s, 1e-11) == min(rows_a, width) for s in c)
    return head + (
        f" ok | {its} | {r['residual']:.1e} | {rows_a}x{cols_a} | "
        f"{_joined(rank(s, 1e-8) for s in a)} | {_joined(rank(s, 1e-13) for s in a)} | "
        f"{_joined(f'{s[0]:.2g}' for s in a)} | {_joined(f'{s[-1]:.1e}' for s in a)} | "
        f"{b.size} | {rank(b, 1e-8)} | {rank(b, 1e-13)} | {b[0]:.2g} | "
        f"{rows_a}x{width} | " + " | ".join(_joined(rank(s, t) for s in c) for t in RTOLS_C)
        + f" | {'yes' if full else 'no'} |"
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="tanh, widths 6 and 10, nodes 8 "
                        "and 16, HO h = 0.1")
    parser.add_argument("--tiny", action="store_true", help="one combination (smoke test)")
    parser.add_argument("--steps", type=int, default=1, help="steps before the measured one "
                        "plus one (default 1: the first step)")
    for field, values in GRID.items():
        parser.add_argument(f"--{field}", nargs="+", default=None,
                            type=str if field in ("problems", "activations") else int,
                            help=f"default {' '.join(map(str, values))}")
    parser.add_argument("--out", default=None, help="file for the table ('-': print only)")
    parser.add_argument("--append", action="store_true", help="append to --out")
    args = parser.parse_args(argv)
    grid = dict(TINY if args.tiny else QUICK if args.quick else GRID)
    for field in GRID:
        if getattr(args, field) is not None:
            grid[field] = getattr(args, field)
    for label in grid["problems"]:
        if label not in PROBLEMS:
            parser.error(f"unknown problem {label!r}; known: {', '.join(PROBLEMS)}")
    for act in grid["activations"]:
        if act not in ACTIVATIONS:
            parser.error(f"unknown activation {act!r}; known: {', '.join(ACTIVATIONS)}")
    if args.steps < 1:
        parser.error("--steps must be at least 1")
    out = args.out
    if out is None:
        out = os.path.join(ROOT, "step_structure_quick.txt" if args.quick
                           else "step_structure.txt")
        if args.tiny:
            out = "-"

    lines = [f"command: {command_line('benchmarks.step_structure', argv)}",
             f"float64; spectra at the converged parameters of step {args.steps} "
             f"(sol.solver_state.theta)", HEADER, "|" + "---|" * HEADER.count(" | ") + "---|"]
    print("\n".join(lines), flush=True)
    fh = None if out == "-" else open(out, "a" if args.append else "w")
    if fh:
        if args.append:
            fh.write("\n")
        fh.write("\n".join(lines) + "\n")
    start = time.perf_counter()
    cache: dict = {}
    # the HO step sizes innermost: they share one compiled solve
    kinds = dict.fromkeys(PROBLEMS[label][0] for label in grid["problems"])
    for kind in kinds:
        labels = [label for label in grid["problems"] if PROBLEMS[label][0] == kind]
        for act in grid["activations"]:
            for width in grid["widths"]:
                for n_nodes in grid["nodes"]:
                    for label in labels:
                        row = measure(label, act, width, n_nodes, args.steps, cache)
                        print(row, flush=True)
                        if fh:
                            fh.write(row + "\n")
                            fh.flush()
    tail = f"wall time {time.perf_counter() - start:.0f} s"
    print(tail)
    if fh:
        fh.write(tail + "\n")
        fh.close()


if __name__ == "__main__":
    main()
