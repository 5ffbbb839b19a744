"""The error estimate's companion step: the classical cGVI of a given degree, solved from
the step's start and seeded by the step's curve; its end state minus the step's is the
estimate (`NetworkVI(error_estimate=...)`).

Which degree, and what the estimate then measures (calibrated against the exact local error;
`benchmarks/adaptive_steps.py`):

- a companion of higher order than the step measures the step's own local error: for
  `CGVI(4)` and `CGVI(6)` the companion of degree `k + 1` gave a median 0.97-1.00x the exact
  local error of the step where that error is above rounding, within 0.74-1.27x on the
  oscillator, Kepler e = 0.5 and Henon-Heiles, 0.47-2.5x on the double pendulum's long
  steps; for the default network the companion of degree 9 gave 0.88-1.09x. Its order in
  `h` is the step's plus one, `2k + 1`;
- a companion of lower order measures its own error, larger than the step's: the
  controller then takes steps of the companion's size and the step is far more accurate
  than asked (the old `error_estimate=3` of the default network: 6.3x the constant steps
  reaching the same error at rtol 1e-12 on the oscillator, 3.7x on Kepler).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from .._ansatz.polynomial import LagrangeBasis
from .._quadrature import GaussLegendre
from .._root_finder.step_hints import StepHints, step_options, traits_of
from .formulation import (
    FreeEndpoints,
    SolveOptions,
    StepContext,
    jacobian_option,
    residual_scale,
)

__all__ = ["check_error_estimate", "companion_degree", "companion_error", "estimate_order"]


def _step_degree(basis) -> int | None:
    """The degree of a polynomial step (`LagrangeBasis`); `None` for a network or any other
    ansatz."""
    return basis.degree if isinstance(basis, LagrangeBasis) else None


def check_error_estimate(estimate, basis) -> None:
    """Raise a `ValueError` unless `estimate` is `None`, `True` or a companion degree >= 1
    that differs from a polynomial step's own degree."""
    if estimate is None or estimate is True:
        return
    if not isinstance(estimate, int) or isinstance(estimate, bool) or estimate < 1:
        raise ValueError(
            "error_estimate must be None (constant steps), True (the default companion) or "
            f"the degree (>= 1) of the companion cGVI, got {estimate!r}"
        )
    degree = _step_degree(basis)
    if estimate == degree:
        raise ValueError(
            f"error_estimate={estimate} is the step's own degree: the companion would be the "
            f"same integrator and estimate nothing. Use error_estimate=True (degree "
            f"{degree + 1}, the step's local error) or another degree"
        )


def companion_degree(estimate, basis, num_nodes: int) -> int | None:
    """The companion's degree: the given one; for `True`, one above a polynomial step's
    degree, and for a network one above the quadrature's number of nodes `n` (the rule's
    order `2n` bounds the network step's; this companion's `2n + 2` is above it: degree
    `n` measured only 0.3-0.6x the network's local error on Kepler, `n + 1` 0.97x)."""
    if estimate is None:
        return None
    if estimate is not True:
        return estimate
    degree = _step_degree(basis)
    return degree + 1 if degree is not None else num_nodes + 1


def estimate_order(estimate, basis, quadrature) -> int | None:
    """The order in `h` of the estimate (diffrax's `error_order`): the local order of the
    less accurate of the step and its companion. The companion of degree `j` has global
    order `2j`; the step at most the quadrature's order `Q`, and a polynomial step of
    degree `k` `min(2k, Q)` (a network's own order is not known in closed form: `Q` bounds
    it)."""
    j = companion_degree(estimate, basis, quadrature.num_nodes)
    if j is None:
        return None
    degree = _step_degree(basis)
    step_order = math.inf if degree is None else 2 * degree
    rule_order = getattr(quadrature, "order", None)
    if rule_order is not None:
        step_order = min(step_order, rule_order)
    return int(min(step_order, 2 * j)) + 1


def companion_error(estimate, options: SolveOptions, ctx: StepContext, curve, q1, p1,
                    ok) -> tuple[Array, Array]:
    """End-state difference to the companion cGVI of `estimate` (a degree, or `True`: see
    `companion_degree`), solved from the same start and seeded by the step's curve (inf
    where the step or the companion failed)."""
    degree = companion_degree(estimate, ctx.basis, ctx.nodes.shape[0])
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
