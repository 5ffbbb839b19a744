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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem", choices=sorted(PROBLEMS))
    parser.add_argument("activation", choices=("gelu", "tanh"))
    parser.add_argument("--target", type=float, default=10.0)
    parser.add_argument("--start", type=float, default=0.05)
    parser.add_argument("--lengths", type=int, default=40,
                        help="lengths of a geometric path from start to target, before "
                             "adapting")
    args = parser.parse_args(argv)
    if not 0 < args.start < args.target:
        parser.error(f"need 0 < start < target, got {args.start} and {args.target}")
    shown = sys.argv[1:] if argv is None else argv
    print("command: python -m benchmarks.root_continuation " + shlex.join(shown))
    print(f"{args.problem}, {args.activation}, width {QUICK_WIDTH[args.problem]}, "
          f"GaussLegendre({QUICK_NODES[args.problem]}), float64, projected step, first step\n")
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
