"""The nonlinear solve of a projected step (`VariableProjection.solve_step`).

The unknowns are the curve's increment coordinates on the span of a hidden layer and
`Δp = p_{n+1} − p_n`. The solve starts from the seed policy's start (the previous curve
continued) and, where that has not converged within `FIRST_TRY` iterations, restarts once
from the trajectory seed projected on the span; the iteration cap covers both tries.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import optimistix as optx

from .._results import from_root_find
from .._root_finder.step_hints import StepHints, step_options, traits_of
from .formulation import SolveOptions, StepContext, StepSolution, residual_scale

__all__ = ["FIRST_TRY", "projected_root_find", "solve_projected", "with_known_span"]

# Iterations the projected step allows its start from the previous curve continued before it
# restarts from the trajectory seed.
FIRST_TRY = 16


def solve_projected(form, ctx: StepContext, options: SolveOptions, hidden, start: Callable,
                    restart_history=None) -> StepSolution:
    """The step's equations of the projection `form` on the feature span of the hidden layer
    of the parameters `hidden`, from the unknowns `start(span)` (a curve projected on the
    span). Given `restart_history` (the steps that start from the previous curve continued),
    a start not converged within `FIRST_TRY` iterations is given up for the seed policy's
    restart point (`options.seeder.restart_point`)."""
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
    z, f = sol.value, sol.state.f
    dtype = ctx.q0.dtype
    eps = float(jnp.finfo(dtype).eps)
    return StepSolution(
        theta=form.expand(form.coefficients(z[0], ctx), span),
        increments=form.projected_increments(z, span, ctx),
        end=None,
        forces=jax.lax.stop_gradient(sol.aux).astype(ctx.p0.dtype),
        iterations=jnp.asarray(sol.stats["num_steps"], jnp.int32),
        result=from_root_find(sol.result),
        residual=jax.lax.stop_gradient(jnp.max(jnp.abs(f)).astype(dtype)),
        tolerance=(options.root_finder.ftol * eps * residual_scale(ctx)).astype(dtype),
        restarted=jnp.asarray(traits_of(options.root_finder).was_restarted(sol.state)),
    )


def projected_root_find(form, options: SolveOptions, ctx: StepContext, span, z0,
                        max_steps: int, restart=None, history=None):
    """`optimistix.root_find` of the projection `form`'s step equations on `span` from `z0`,
    with the hints the step hands its root finder (residual scale, Jacobian, kinetic matrix,
    the iteration cap, and the restart `(first_try, start)` where given). Its `aux` is the
    forces at the nodes of the final iterate, and `stats["num_steps"]` the iterations made
    (by a root finder that runs the whole solve in one optimistix step, too)."""
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
    )
    root_finder = options.root_finder
    sol = optx.root_find(
        reading(form.reduced_residual_and_forces), root_finder, z0, (ctx, span, history),
        options=step_options(hints), has_aux=True,
        max_steps=max_steps, adjoint=options.adjoint, throw=False,
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
