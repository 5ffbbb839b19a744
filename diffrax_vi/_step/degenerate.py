"""Lagrangians linear in the velocities (first-order, degenerate): the primary constraint.

Where `ϑ = ∂L/∂v` does not depend on `v` (an IODE such as the degenerate pendulum,
`L = ϑ(q)·v − H(q)`), the flow keeps the state on `p = ϑ(t, q)`. A step's end state can leave
that constraint without its residual showing it; these helpers put `q_{n+1}` back on it
(`first_order_end_correction`, used by the projected step) and measure how far an end state
is off it (`primary_constraint_violation`, which every step reports and the all-parameter
network step checks against `CONSTRAINT_TOLERANCE` and `CONSTRAINT_GROWTH`). The step calls
both through `end_on_constraint`, which tests once whether `ϑ` reads `v` and skips both for
any other Lagrangian.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._precision import lapack_dtype
from .formulation import StepContext
from .kinetic_check import kinetic_matrix_regular

__all__ = [
    "CONSTRAINT_GROWTH",
    "CONSTRAINT_TOLERANCE",
    "end_on_constraint",
    "first_order_end_correction",
    "primary_constraint_violation",
]

# An all-parameter network step of a first-order Lagrangian fails
# (`RESULTS.vi_constraint_drift`) where its end state is further than
# `eps ** CONSTRAINT_TOLERANCE` (half the working digits) off the primary constraint, relative
# to the step's residual scale `1 + max(|q_n|, |p_n|)`, and more than `CONSTRAINT_GROWTH`
# times as far as the run's first step was.
CONSTRAINT_TOLERANCE = 0.5
CONSTRAINT_GROWTH = 100.0


def _momentum_map(ctx: StepContext):
    """`q ↦ ϑ(t_{n+1}, q, v = 0)`, and `(q, v) ↦ ϑ(t_{n+1}, q, v)`."""
    t = ctx.t + ctx.h

    def theta(q, v):
        return ctx.term.momentum(t, q, v, ctx.args)

    return lambda q: theta(q, jnp.zeros_like(q)), theta


def _first_order_at(theta, q1: Array) -> Array:
    """Whether `∂ϑ/∂v` vanishes at `(q1, v = 0)` (a first-order end point); not
    differentiated."""
    jv = jax.lax.stop_gradient(jax.jacfwd(lambda v: theta(q1, v))(jnp.zeros_like(q1)))
    return jnp.all(jv == 0)


def _gauss_newton_onto(theta, q1: Array, p1: Array) -> Array:
    """`(∂ϑ/∂q)^+ (p1 − ϑ(q1))` for `theta = q ↦ ϑ(q, v = 0)`, the pseudo-inverse by SVD
    (`jnp.linalg.pinv` would put a float64 constant into float32 steps)."""
    jq = jax.lax.stop_gradient(jax.jacfwd(theta)(q1))
    work = lapack_dtype(q1.dtype)
    u, sv, vt = jnp.linalg.svd(jq.astype(work))
    kept = sv > 10 * max(jq.shape) * jnp.finfo(work).eps * sv[0]
    inv = jnp.where(kept, 1 / jnp.where(kept, sv, 1), 0)
    misfit = (p1 - theta(q1)).astype(work)
    return (vt.T @ (inv * (u.T @ misfit))).astype(q1.dtype)


def _gap(theta, q1: Array, p1: Array) -> Array:
    """`max|p1 − ϑ(q1)|`, not differentiated."""
    return jax.lax.stop_gradient(jnp.max(jnp.abs(p1 - theta(q1))))


def first_order_end_correction(ctx: StepContext, q1: Array, p1: Array) -> Array:
    """The change of `q_{n+1}` that a first-order Lagrangian's end state needs; zero for
    any other.

    The step's `p_{n+1}` is the natural boundary value of the discrete action and inherits its
    superconvergence, but the coordinates that `ϑ` reads enter the action undifferentiated:
    `q_h(1)` extrapolates them from the nodes, with the span's own (first-order) error. One
    Gauss–Newton update, `Δq = (∂ϑ/∂q)^+ (p_{n+1} − ϑ(q_h(1)))`, takes them from `p_{n+1}`
    instead and leaves the others as they are. When `∂ϑ/∂v` has any nonzero entry at the end
    point the change is zero.
    """
    at_rest, theta = _momentum_map(ctx)
    step = _gauss_newton_onto(at_rest, q1, p1)
    return jnp.where(_first_order_at(theta, q1), step, jnp.zeros_like(step))


def primary_constraint_violation(ctx: StepContext, q1: Array, p1: Array) -> Array:
    """`max|p_{n+1} − ϑ(t_{n+1}, q_{n+1})|` where `ϑ` does not depend on `v` at the end point
    (a first-order Lagrangian), else 0; not differentiated."""
    at_rest, theta = _momentum_map(ctx)
    gap = _gap(at_rest, q1, p1)
    return jnp.where(_first_order_at(theta, q1), gap, jnp.zeros_like(gap))


def end_on_constraint(ctx: StepContext, q1: Array, p1: Array, correct: bool = True
                      ) -> tuple[Array, Array]:
    """`(q_{n+1}, violation)`: the end position moved onto the primary constraint
    (`first_order_end_correction`, with `correct`; else `q1` as it is) and its distance
    from the constraint there (`primary_constraint_violation`).

    The test (`∂ϑ/∂v` at the end point) is the only derivative a regular Lagrangian's step
    pays for: one `lax.cond` on it returns `q1` and a zero violation, which is what the two
    functions give there, and only a first-order end state forms `∂ϑ/∂q` and the SVD of the
    correction (where `ϑ` does not read `v` at `q1`, it does not at the moved point either:
    the move is of the size of the step's error)."""
    if kinetic_matrix_regular(ctx):  # never first order but at special states: nothing to do
        return q1, jnp.zeros((), jnp.result_type(q1, p1))
    at_rest, theta = _momentum_map(ctx)

    def on_constraint(q1, p1):
        moved = q1 + _gauss_newton_onto(at_rest, q1, p1) if correct else q1
        return moved, _gap(at_rest, moved, p1).astype(jnp.result_type(q1, p1))

    def regular(q1, p1):
        return q1, jnp.zeros((), jnp.result_type(q1, p1))

    return jax.lax.cond(_first_order_at(theta, q1), on_constraint, regular, q1, p1)
