"""Does the projected step have a root at a long step? Follow it from a short one.

The stability sweep's projected step fails its dt = 10 cases on the pendulum and the double
pendulum: neither the previous curve continued nor the trajectory seed starts Newton's method
close enough. This script asks whether a root is there at all, by continuation in the step
length: the first step of the problem is solved at `h₀` (from the constant curve), and each
solution, stretched in time to the next, longer `h` (its curve at `τ h / h_prev`, and its end
momentum), starts the next solve, up to the target. The ratio between consecutive lengths
shrinks (square root) after a failed solve and grows again after an easy one (at most 4
iterations), so the path is followed as far as it goes.

Reaching the target shows a root exists there, on the branch that the short step's root
continues to; stopping short shows that branch folds (other branches may exist). The error
of the end position against the problem's reference is printed relative to `1 + |q₀|`: at
steps of the motion's own time scale a root is a far too coarse discretisation, and its error
says so.

    .venv/bin/python -m benchmarks.root_continuation pendulum tanh --target 10

A folding branch does not rule out roots on other branches. `--random-starts N` solves the
first step at the target directly from `N` random curves instead (end position uniform in
`q₀ ± π`, a random half-sine bulge of amplitude up to π in each coordinate, end momentum
`p₀` plus a normal draw of deviation `--momentum-scale`), with the stability sweep's cap of
1000 iterations, and counts the starts that converge and the distinct end states they reach:

    .venv/bin/python -m benchmarks.root_continuation double_pendulum tanh --target 10 \
        --random-starts 256
"""

from __future__ import annotations

import argparse
import shlex
import sys

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from diffrax_vi.bench.stability import PROBLEMS, QUICK_NODES, QUICK_WIDTH, StabilityCase  # noqa: E402
from diffrax_vi.step_solve import solve_projected  # noqa: E402


def projected_start(solver, ctx, curve, p1):
    """The projected step's start from a curve and an end momentum (`solve_projected`)."""
    return lambda span: solver.formulation.start(curve, p1, span, ctx)


def follow(problem_name: str, activation: str, target: float, *, start: float = 0.05,
           lengths: int = 40, max_solves: int = 400):
    """Continuation from `start` to `target`; returns the rows `(h, iterations, residual,
    error)` of the accepted solves, the length reached, and the solves tried."""
    case = StabilityCase(problem_name, target, "float64", QUICK_NODES[problem_name],
                         QUICK_WIDTH[problem_name], activation, "projection")
    solver = case.build()
    problem = PROBLEMS[problem_name](dtype=np.float64)
    term, y0, t0 = problem.term, problem.y0, problem.t0
    hidden = solver.formulation.hidden.parameters(solver.basis, y0[0].shape[0], jnp.float64)
    scale = 1.0 + float(np.max(np.abs(np.asarray(y0[0]))))

    @jax.jit
    def solve(h, theta, h_prev, p1):
        ctx = solver.step_context(term, t0, t0 + h, y0, problem.args)

        def stretched(tau):
            return solver.basis.evaluate(theta, tau * h / h_prev)

        return solve_projected(solver, ctx, hidden, projected_start(solver, ctx, stretched, p1))

    @jax.jit
    def first(h):
        ctx = solver.step_context(term, t0, t0 + h, y0, problem.args)
        return solve_projected(
            solver, ctx, hidden, projected_start(solver, ctx, lambda tau: y0[0], y0[1])
        )

    solved = first(jnp.asarray(start))
    theta, (_, dp), result = solved.theta, solved.increments, solved.result
    if result != diffrax.RESULTS.successful:
        return [], 0.0, 1
    rows, h_prev, p1 = [], start, y0[1] + dp
    ratio = (target / start) ** (1 / (lengths - 1))
    solves = 1
    while h_prev < target and solves < max_solves and ratio > 1 + 1e-4:
        h = min(h_prev * ratio, target)
        out = solve(jnp.asarray(h), theta, jnp.asarray(h_prev), p1)
        theta_new, (dq, dp), n, result, residual = (
            out.theta, out.increments, out.iterations, out.result, out.residual
        )
        solves += 1
        if result != diffrax.RESULTS.successful:
            ratio = ratio**0.5
            continue
        q_ref = problem.reference(np.array([t0 + h]))[0][0]
        error = float(np.max(np.abs(np.asarray(y0[0] + dq) - q_ref))) / scale
        rows.append((h, int(n), float(residual), error))
        theta, h_prev, p1 = theta_new, h, y0[1] + dp
        if int(n) <= 4:
            ratio = ratio**1.5
    return rows, h_prev, solves


def random_starts(problem_name: str, activation: str, h: float, count: int, *,
                  seed: int = 0, momentum_scale: float = 10.0, max_iterations: int = 1000):
    """The first step at `h` from `count` random curves (see the module's docstring), solved
    together under `vmap`. Returns per start: whether it converged, its iterations, its
    final residual, and the end position and momentum."""
    case = StabilityCase(problem_name, h, "float64", QUICK_NODES[problem_name],
                         QUICK_WIDTH[problem_name], activation, "projection",
                         max_iterations=max_iterations)
    solver = case.build()
    problem = PROBLEMS[problem_name](dtype=np.float64)
    term, y0, t0 = problem.term, problem.y0, problem.t0
    q0, p0 = (jnp.asarray(y) for y in y0)
    hidden = solver.formulation.hidden.parameters(solver.basis, q0.shape[0], jnp.float64)
    rng = np.random.default_rng(seed)
    d = q0.shape[0]
    ends = np.asarray(q0) + rng.uniform(-np.pi, np.pi, (count, d))
    bulges = rng.uniform(-np.pi, np.pi, (count, d))
    momenta = np.asarray(p0) + momentum_scale * rng.standard_normal((count, d))

    @jax.jit
    @jax.vmap
    def solve(q1, bulge, p1):
        ctx = solver.step_context(term, t0, t0 + h, y0, problem.args)

        def curve(tau):
            return q0 + (q1 - q0) * tau + bulge * jnp.sin(jnp.pi * tau)

        out = solve_projected(solver, ctx, hidden, projected_start(solver, ctx, curve, p1))
        dq, dp = out.increments
        return out.result == diffrax.RESULTS.successful, out.iterations, out.residual, \
            q0 + dq, p0 + dp

    ok, n, residual, q_end, p_end = solve(jnp.asarray(ends), jnp.asarray(bulges),
                                           jnp.asarray(momenta))
    return (np.asarray(ok), np.asarray(n), np.asarray(residual), np.asarray(q_end),
            np.asarray(p_end))


def distinct(points: np.ndarray, tolerance: float = 1e-8) -> list[np.ndarray]:
    """The points that differ from every earlier one by more than `tolerance` (max-norm)."""
    kept: list[np.ndarray] = []
    for x in points:
        if all(np.max(np.abs(x - y)) > tolerance for y in kept):
            kept.append(x)
    return kept


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem", choices=sorted(PROBLEMS))
    parser.add_argument("activation", choices=("gelu", "tanh"))
    parser.add_argument("--target", type=float, default=10.0)
    parser.add_argument("--start", type=float, default=0.05)
    parser.add_argument("--lengths", type=int, default=40,
                        help="lengths of a geometric path from start to target, before "
                             "adapting")
    parser.add_argument("--random-starts", type=int, default=0, metavar="N",
                        help="solve at the target from N random curves instead of continuing")
    parser.add_argument("--momentum-scale", type=float, default=10.0,
                        help="deviation of the random starts' end momenta from p0")
    parser.add_argument("--seed", type=int, default=0, help="of the random starts")
    args = parser.parse_args(argv)
    if args.random_starts < 0:
        parser.error(f"--random-starts must not be negative, got {args.random_starts}")
    if not 0 < args.start < args.target:
        parser.error(f"need 0 < start < target, got {args.start} and {args.target}")
    shown = sys.argv[1:] if argv is None else argv
    print("command: python -m benchmarks.root_continuation " + shlex.join(shown))
    print(f"{args.problem}, {args.activation}, width {QUICK_WIDTH[args.problem]}, "
          f"GaussLegendre({QUICK_NODES[args.problem]}), float64, projected step, first step\n")
    if args.random_starts:
        ok, n, residual, q_end, p_end = random_starts(
            args.problem, args.activation, args.target, args.random_starts, seed=args.seed,
            momentum_scale=args.momentum_scale)
        print(f"h = {args.target}: {int(ok.sum())} of {args.random_starts} random starts "
              f"converge (seed {args.seed}, momentum scale {args.momentum_scale})")
        if ok.any():
            roots = distinct(np.concatenate([q_end[ok], p_end[ok]], axis=1))
            problem = PROBLEMS[args.problem](dtype=np.float64)
            q_ref = problem.reference(np.array([problem.t0 + args.target]))[0][0]
            scale = 1.0 + float(np.max(np.abs(np.asarray(problem.y0[0]))))
            print(f"distinct end states (to 1e-8): {len(roots)}; iterations of the converged "
                  f"starts: median {int(np.median(n[ok]))}, max {int(n[ok].max())}")
            print("| end q | end p | rel. error of q(h) |")
            print("|---|---|---|")
            for root in roots:
                qe, pe = root[: q_ref.shape[0]], root[q_ref.shape[0]:]
                error = float(np.max(np.abs(qe - q_ref))) / scale
                print(f"| {np.array2string(qe, precision=4)} | "
                      f"{np.array2string(pe, precision=4)} | {error:.1e} |")
        stalled = ~ok
        if stalled.any():
            print(f"unconverged starts: residual max|F| median {np.median(residual[stalled]):.1e}"
                  f", min {residual[stalled].min():.1e}")
        return
    rows, reached, solves = follow(args.problem, args.activation, args.target,
                                   start=args.start, lengths=args.lengths)
    print("| h | iterations | residual max|F| | rel. error of q(h) |")
    print("|---|---|---|---|")
    for h, n, residual, error in rows:
        print(f"| {h:.3f} | {n} | {residual:.1e} | {error:.1e} |")
    verdict = "reached" if reached >= args.target else "stopped at"
    print(f"\n{verdict} h = {reached:.3f} after {solves} solves")


if __name__ == "__main__":
    main()
