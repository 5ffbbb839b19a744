"""The nonlinear solve of a projected step (`VariableProjection.solve_step`).

The unknowns are the curve's increment coordinates on the span of a hidden layer and
`Δp = p_{n+1} − p_n`. Where the root finder allows it and the step offers it (a span known
when the step is traced, a constant kinetic matrix: `_step.jacobian_free.picard_engine`),
the solve is `JacobianFreeIteration`'s, from the last step's node values continued;
elsewhere it is the root finder's own, from the seed policy's start (the previous curve
continued) and, where that has not converged within `FIRST_TRY` iterations, once more from
the trajectory seed projected on the span (with `restart=True`); the iteration cap covers
both tries. Either way it is one root find, differentiated by the solver's adjoint.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

from .._results import from_root_find
from .._root_finder.jacobian_free import JacobianFreeIteration
from .._root_finder.solve import step_root_find
from .._root_finder.step_hints import StepHints, step_options, traits_of
from .formulation import SolveOptions, StepContext, StepSolution, residual_scale
from .jacobian_free import end_increments, end_offsets, engine_start, engine_update

__all__ = ["FIRST_TRY", "projected_root_find", "solve_projected", "with_known_span"]

# Iterations the projected step allows its start from the previous curve continued before it
# restarts from the trajectory seed.
FIRST_TRY = 16


def solve_projected(form, ctx: StepContext, options: SolveOptions, hidden, start: Callable,
                    restart_history=None, engine=None) -> StepSolution:
    """The step's equations of the projection `form` on the feature span of the hidden layer
    of the parameters `hidden`, from the unknowns `start(span)` (a curve projected on the
    span). Given `restart_history` (the steps that start from the previous curve continued),
    a start not converged within `FIRST_TRY` iterations is given up for the seed policy's
    restart point (`options.seeder.restart_point`). Given `engine = (Engine, node values)`
    (the seed policy's, where the step takes the Jacobian-free iteration), the solve starts
    from the unknowns those node values give and is `JacobianFreeIteration`'s."""
    if engine is not None:
        return _solve_by_engine(form, ctx, options, *engine)
    span = form.span(hidden, ctx)
    z0 = jax.lax.stop_gradient(start(span))
    cap = options.max_steps
    restart = None
    if restart_history is not None and cap > FIRST_TRY:
        # Inside the root finder, so that the restart point is computed only where a solve
        # needs it, and under vmap only if some member does.
        seeder = options.seeder

        def restart_start(args):
            ctx, span, history = args
            return seeder.restart_point(ctx, span, history)

        restart = (FIRST_TRY, restart_start)
    sol = projected_root_find(form, options, ctx, span, z0, cap, restart, restart_history)
    return _solution(form, options, ctx, span, sol, options.root_finder)


def _solution(form, options: SolveOptions, ctx: StepContext, span, sol, root_finder
              ) -> StepSolution:
    """The step's solution from `projected_root_find`'s by `root_finder`."""
    z = sol.value
    dtype = ctx.q0.dtype
    eps = float(jnp.finfo(dtype).eps)
    return StepSolution(
        theta=form.expand(form.coefficients(z[0], ctx), span),
        increments=form.projected_increments(z, span, ctx),
        end=None,
        forces=jax.lax.stop_gradient(sol.aux).astype(ctx.p0.dtype),
        iterations=jnp.asarray(sol.stats["num_steps"], jnp.int32),
        result=from_root_find(sol.result),
        residual=jax.lax.stop_gradient(jnp.max(jnp.abs(sol.state.f)).astype(dtype)),
        tolerance=(options.root_finder.ftol * eps * residual_scale(ctx)).astype(dtype),
        restarted=jnp.asarray(traits_of(root_finder).was_restarted(sol.state)),
    )


def _solve_by_engine(form, ctx: StepContext, options: SolveOptions, engine, values
                     ) -> StepSolution:
    """The step by `JacobianFreeIteration` (falling back to Newton's iteration where the
    solver's root finder asks for it: `picard_fallback`), from the node values
    `values = (F, G)` continued; the solution's `node_values` are those of its curve, for
    the next step's start."""
    span = engine.span
    z0 = jax.lax.stop_gradient(engine_start(engine, ctx, values))
    fallback = traits_of(options.root_finder).picard_falls_back()
    iteration = JacobianFreeIteration(newton_fallback=fallback)
    sol = projected_root_find(form, options, ctx, span, z0, options.max_steps,
                              engine_update=engine_update(engine), root_finder=iteration)
    solved = _solution(form, options, ctx, span, sol, iteration)
    offsets = jax.lax.stop_gradient(end_offsets(engine, ctx, sol.value, values[1]))
    # the end's increment summed accurately (`end_increments`: its rounding is a drift)
    return solved._replace(increments=end_increments(engine, ctx, sol.value),
                           node_values=(solved.forces, offsets.astype(ctx.p0.dtype)))


def projected_root_find(form, options: SolveOptions, ctx: StepContext, span, z0,
                        max_steps: int, restart=None, history=None, *, engine_update=None,
                        root_finder=None):
    """`optimistix.root_find` of the projection `form`'s step equations on `span` from `z0`,
    with the hints the step hands its root finder (residual scale, Jacobian, kinetic matrix,
    the iteration cap, and the restart `(first_try, start)` where given). Its `aux` is the
    forces at the nodes of the final iterate, and `stats["num_steps"]` the iterations made
    (by a root finder that runs the whole solve in one optimistix step, too). Given
    `engine_update` (the step's Jacobian-free update), the hints offer it, with the residual
    in its faster form; `root_finder` replaces the solver's."""
    fixed = with_known_span(span)

    def reading(f):
        return lambda z, args: f(z, fixed(args))

    if restart is not None:
        first_try, start = restart
        restart = (first_try, lambda args: start(fixed(args)))
    hints = StepHints(
        scale=residual_scale(ctx),
        jacobian=reading(form.reduced_jacobian),
        inverse=lambda jacobian, z, args: form.invert_reduced_jacobian(jacobian, z),
        kinetic=reading(
            functools.partial(form.kinetic_inverse, uniform=form.uniform_span(span))
        ),
        max_iterations=max_steps,
        restart=restart,
        update=engine_update,
        fast_residual=None if engine_update is None else reading(
            functools.partial(form.reduced_residual_and_forces, fused=True)),
    )
    root_finder = options.root_finder if root_finder is None else root_finder
    sol = step_root_find(
        reading(form.reduced_residual_and_forces), root_finder, z0, (ctx, span, history),
        step_options(hints), has_aux=True, max_steps=max_steps, adjoint=options.adjoint,
    )
    if traits_of(root_finder).reads_hint("max_iterations"):
        sol = dataclasses.replace(sol, stats={**sol.stats, "num_steps": sol.state.iterations})
    return sol


def with_known_span(span) -> Callable[[tuple], tuple]:
    """`args = (ctx, span, history) ↦ args` with `span` in place of the one in `args` where
    `span` is known when the step is traced (a linear ansatz, a fixed hidden layer).
    optimistix traces the `args` of a root find, so the span would reach the compiled solve
    as a variable and every product with it would run as a kernel of its own; taken from
    here it stays a constant that XLA folds, and the formulation can use its structure
    (`uniform_span`)."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(span)):
        return lambda args: args
    return lambda args: (args[0], span, *args[2:])
