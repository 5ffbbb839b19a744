"""The error estimate's companion step: the classical cGVI of a given degree, solved from
the step's start and seeded by the step's curve; its end state minus the step's is the
estimate (`NetworkVI(error_estimate=...)`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from .ansatz.polynomial import LagrangeBasis
from .formulation import (
    FreeEndpoints,
    SolveOptions,
    StepContext,
    jacobian_option,
    residual_scale,
)
from .quadrature import GaussLegendre
from .root_finders.step_hints import StepHints, step_options, traits_of

__all__ = ["companion_error"]


def companion_error(degree: int, options: SolveOptions, ctx: StepContext, curve, q1, p1,
                    ok) -> tuple[Array, Array]:
    """End-state difference to the cGVI of `degree`, solved from the same start and seeded by
    the step's curve (inf where the step or the companion failed)."""
    basis = LagrangeBasis(degree)
    nodes, weights = GaussLegendre(degree + 1).nodes_weights(ctx.q0.dtype)
    companion = StepContext(
        ctx.term, basis, ctx.t, ctx.h, ctx.q0, ctx.p0, ctx.args, nodes, weights
    )
    points = jnp.asarray(basis.control_points, ctx.q0.dtype)
    seed = jax.lax.stop_gradient((jax.vmap(curve)(points), p1))
    form = FreeEndpoints()
    # The companion solves all its coefficients, which the step's root finder may not suit.
    root_finder = traits_of(options.root_finder).companion()
    if root_finder is None:
        root_finder = options.root_finder
    sol = optx.root_find(
        lambda x, c: form.residual(x, c),
        root_finder,
        seed,
        companion,
        options=step_options(StepHints(
            scale=residual_scale(ctx), outputs=lambda x: form.end_state(x, companion),
            jacobian=jacobian_option(root_finder, form, companion),
        )),
        max_steps=options.max_steps,
        adjoint=options.adjoint,
        throw=False,
    )
    qc, pc = form.end_state(sol.value, companion)
    good = ok & (sol.result == optx.RESULTS.successful)
    inf = jnp.asarray(jnp.inf, ctx.q0.dtype)
    eq = jnp.where(good, (q1 - qc).astype(ctx.q0.dtype), inf)
    ep = jnp.where(good, (p1 - pc).astype(ctx.p0.dtype), inf)
    return jax.lax.stop_gradient((eq, ep))
