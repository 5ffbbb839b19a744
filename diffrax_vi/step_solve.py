"""The nonlinear solve of one `NetworkVI` step, in its two forms, and the error estimate's.

- `solve_projected`: the projected step (`VariableProjection`): the curve's increment
  coordinates on the span of a hidden layer, and `Δp`, with a restart from the trajectory seed
  where the start from the previous curve does not converge.
- `solve_all`: the reference's all-parameter step, from the seed policy's start and fallback.
- `companion_error`: the end-state difference to the cGVI of degree `error_estimate`.

Each takes the solver whose options it reads (`formulation`, `root_finder`,
`root_find_max_steps`, `adjoint`, the seed policy).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .ansatz.polynomial import LagrangeBasis
from .formulation import AbstractFormulation, FreeEndpoints, StepContext
from .quadrature import GaussLegendre
from .results import from_root_find
from .root_finders.damped_newton import AbstractDampedNewton, LevenbergMarquardt
from .root_finders.newton import RoundoffNewton
from .root_finders.step_hints import StepHints, step_options
from .seeding.policy import Seed
from .seeding.policy import residual_scale as _residual_scale

__all__ = [
    "FIRST_TRY", "ProjectedSolve", "companion_error", "jacobian_option",
    "projected_root_find", "solve_all", "solve_projected", "with_known_span",
]

# Iterations the projected step allows its start from the previous curve continued before it
# restarts from the trajectory seed.
FIRST_TRY = 16


class ProjectedSolve(NamedTuple):
    """How a projected step's solve ended (`solve_projected`).

    - `theta`: the converged curve as ansatz parameters;
    - `unknowns`: the solution `z = (δc, Δp)` in the span's increment coordinates;
    - `increments`: `(q_{n+1} − q_n, Δp)`, each to the rounding of its own size;
    - `forces`: `∂L/∂q` at the nodes of the converged curve (`(R, D)`), for dense output;
    - `iterations`, `result`, `residual` (final `max|F|`), `tolerance` (the residual it had
      to reach), `restarted` (whether it restarted from the trajectory seed).
    """

    theta: Any
    unknowns: tuple[Array, Array]
    increments: tuple[Array, Array]
    forces: Array
    iterations: Array
    result: Any
    residual: Array
    tolerance: Array
    restarted: Array


def solve_projected(vi: Any, ctx: StepContext, hidden, start: Callable,
                    restart_history=None) -> ProjectedSolve:
    """The step's equations on the feature span of the hidden layer of the parameters
    `hidden`, from the unknowns `start(span)` (the seed policy's start: a curve projected
    on the span).

    Given `restart_history` (the steps that start from the previous curve continued), a start
    that has not converged within `FIRST_TRY` iterations is given up for the trajectory seed of
    `initial_trajectory` (its labels, piecewise linear in `τ`) projected on the span; the
    iteration cap covers both tries."""
    form = vi.formulation
    span = form.span(hidden, ctx)
    z0 = jax.lax.stop_gradient(start(span))
    cap = vi.root_find_max_steps
    restart = None
    if restart_history is not None and cap > FIRST_TRY:
        # Inside the root finder, so that the trajectory seed is computed only where a solve
        # needs it, and under vmap only if some member does.
        seeding = vi.seeder

        def restart_start(args):
            ctx, span, history = args
            return seeding.restart_point(ctx, span, history)

        restart = (FIRST_TRY, restart_start)
    sol = projected_root_find(vi, ctx, span, z0, cap, restart, restart_history)
    z, f, n = sol.value, sol.state.f, jnp.asarray(sol.stats["num_steps"], jnp.int32)
    restarted = jnp.asarray(getattr(sol.state, "restarted", False))
    theta = form.expand(form.coefficients(z[0], ctx), span)
    increments = form.projected_increments(z, span, ctx)
    dtype = ctx.q0.dtype
    residual = jax.lax.stop_gradient(jnp.max(jnp.abs(f)).astype(dtype))
    eps = float(jnp.finfo(dtype).eps)
    tolerance = (vi.root_finder.ftol * eps * _residual_scale(ctx)).astype(dtype)
    forces = jax.lax.stop_gradient(sol.aux).astype(ctx.p0.dtype)
    return ProjectedSolve(theta, z, increments, forces, n, from_root_find(sol.result),
                          residual, tolerance, restarted)


def projected_root_find(vi: Any, ctx: StepContext, span, z0, max_steps: int, restart=None,
                        history=None):
    """`optimistix.root_find` of the projected step's equations on `span` from `z0`, with the
    options the solver hands its root finder (residual scale, Jacobian, kinetic matrix, the
    iteration cap, and the restart `(first_try, start)` where given). Its `aux` is the forces
    at the nodes of the final iterate, and `stats["num_steps"]` the iterations made (by a
    root finder that runs the whole solve in one optimistix step, too)."""
    form = vi.formulation
    fixed = with_known_span(span)

    def reading(f):
        return lambda z, args: f(z, fixed(args))

    if restart is not None:
        first_try, start = restart
        restart = (first_try, lambda args: start(fixed(args)))
    hints = StepHints(
        scale=_residual_scale(ctx),
        jacobian=reading(form.reduced_jacobian),
        inverse=lambda jacobian, z, args: form.invert_reduced_jacobian(jacobian, z),
        kinetic=reading(
            functools.partial(form.kinetic_inverse, uniform=form.uniform_span(span))
        ),
        max_iterations=max_steps,
        restart=restart,
    )
    sol = optx.root_find(
        reading(form.reduced_residual_and_forces), vi.root_finder, z0, (ctx, span, history),
        options=step_options(hints), has_aux=True,
        max_steps=max_steps, adjoint=vi.adjoint, throw=False,
    )
    if "max_iterations" in getattr(vi.root_finder, "hints_read", ()):
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


def solve_all(vi: Any, ctx: StepContext, seed: Seed):
    """The step's equations in all the ansatz parameters (the reference's solve), from `seed`
    with the seed policy's fallback. Returns the parameters, the end state, the iterations,
    the result, the final residual and its tolerance, and whether it restarted."""
    x0, seed_args, fallback = vi.seeder.root_find_start(seed)
    jacobian = jacobian_option(vi.root_finder, vi.formulation, ctx)
    hints = dataclasses.replace(
        fallback,
        scale=_residual_scale(ctx),
        outputs=lambda x: vi.formulation.end_state(x, ctx),
        jacobian=None if jacobian is None else lambda x, a: jacobian(x, a[0]),
    )
    sol = optx.root_find(
        lambda x, a: vi.formulation.residual(x, a[0]), vi.root_finder, x0, (ctx, *seed_args),
        options=step_options(hints), max_steps=vi.root_find_max_steps, adjoint=vi.adjoint,
        throw=False,
    )
    x = sol.value
    residual, tolerance = _final_residual(vi, sol, ctx)
    n = jnp.asarray(sol.stats["num_steps"], jnp.int32)
    restarted = jnp.asarray(getattr(sol.state, "restarted", False))
    return (
        x[0], vi.formulation.end_state(x, ctx), n, from_root_find(sol.result), residual,
        tolerance, restarted,
    )


def _final_residual(vi: Any, sol, ctx: StepContext) -> tuple[Array, Array]:
    """`max|F|` where the step's solve stopped, and the residual it needed to reach."""
    dtype = ctx.q0.dtype
    if isinstance(vi.root_finder, AbstractDampedNewton):
        f = sol.state.f
        ftol = vi.root_finder.tolerances(dtype)["ftol"]
        tolerance = (ftol * _residual_scale(ctx)).astype(dtype)
    else:
        f = ravel_pytree(vi.formulation.residual(sol.value, ctx))[0]
        tolerance = jnp.full((), jnp.nan, dtype)
    residual = jnp.max(jnp.abs(f)).astype(dtype)
    return jax.lax.stop_gradient(residual), tolerance


def companion_error(vi: Any, ctx: StepContext, curve, q1, p1, ok) -> tuple[Array, Array]:
    """End-state difference to the cGVI of degree `vi.error_estimate`, solved from the same
    start and seeded by the step's curve (inf where the step or the companion failed)."""
    degree = vi.error_estimate
    basis = LagrangeBasis(degree)
    nodes, weights = GaussLegendre(degree + 1).nodes_weights(ctx.q0.dtype)
    companion = StepContext(
        ctx.term, basis, ctx.t, ctx.h, ctx.q0, ctx.p0, ctx.args, nodes, weights
    )
    points = jnp.asarray(basis.control_points, ctx.q0.dtype)
    seed = jax.lax.stop_gradient((jax.vmap(curve)(points), p1))
    form = FreeEndpoints()
    # The companion solves all its coefficients: a damped root finder.
    root_finder = (
        LevenbergMarquardt() if isinstance(vi.root_finder, RoundoffNewton) else vi.root_finder
    )
    sol = optx.root_find(
        lambda x, c: form.residual(x, c),
        root_finder,
        seed,
        companion,
        options=step_options(StepHints(
            scale=_residual_scale(ctx), outputs=lambda x: form.end_state(x, companion),
            jacobian=jacobian_option(root_finder, form, companion),
        )),
        max_steps=vi.root_find_max_steps,
        adjoint=vi.adjoint,
        throw=False,
    )
    qc, pc = form.end_state(sol.value, companion)
    good = ok & (sol.result == optx.RESULTS.successful)
    inf = jnp.asarray(jnp.inf, ctx.q0.dtype)
    eq = jnp.where(good, (q1 - qc).astype(ctx.q0.dtype), inf)
    ep = jnp.where(good, (p1 - pc).astype(ctx.p0.dtype), inf)
    return jax.lax.stop_gradient((eq, ep))


def jacobian_option(root_finder, formulation: AbstractFormulation, ctx: StepContext):
    """The Jacobian the solver hands its root finder (the hint `jacobian`, a function of the
    unknowns and the step context): the block assembly of `formulation` where the root finder
    asks for it (`jacobian="structured"`), or leaves the choice to us (`"auto"`) and the blocks
    have a closed form; else `None`. The context comes in as the root find's `args`, not by
    closure, so that implicit differentiation of the step sees it."""
    mode = getattr(root_finder, "jacobian", None)
    if mode == "structured" or (
        mode == "auto" and formulation.has_closed_form_jacobian(ctx.basis)
    ):
        return formulation.jacobian
    return None
