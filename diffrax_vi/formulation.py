"""The discrete action of one step and the variational equations built from it.

On a step `[t_n, t_n + h]` with local time `τ ∈ [0, 1]` and a quadrature rule `(c_j, b_j)`,
the discrete action of a trial curve `q_h(τ; θ)` is

    A(θ) = h Σ_j b_j L(t_n + c_j h, q_h(c_j), q_h'(c_j) / h).

Its gradient is assembled from the momentum `ϑ = ∂L/∂v` and force `f = ∂L/∂q` at the nodes,
pulled back through the stage map `θ ↦ (q_h(c_j), q_h'(c_j))` by one vector-Jacobian product:

    ∂A/∂θ = Σ_j b_j [ h f_j · ∂q_h(c_j)/∂θ + ϑ_j · ∂q_h'(c_j)/∂θ ].

For a `LagrangianTerm` this is exactly `jax.grad` of `A`; written through `(ϑ, f)` it also
covers degenerate systems given only by those maps (`IODETerm`).

**Free endpoints** (the reference's ShallowNet family): unknowns `θ` and `p_{n+1}`, equations

    ∂/∂θ [ p_{n+1}·q_h(1) − p_n·q_h(0) − A(θ) ] = 0,      q_n − q_h(0) = 0,

then `q_{n+1} = q_h(1)`. Each equation sits at the position of "its" unknown (the rows of `θ`,
then continuity at the position of `p_{n+1}`), which matters for the `J + λI` regularisation.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .ansatz.base import AbstractBasis
from .terms import AbstractMechanicalTerm

__all__ = ["StepContext", "FreeEndpoints", "action_gradient", "stage_values"]


class StepContext(eqx.Module):
    """Everything the equations of one step depend on (the `args` of the root find)."""

    term: AbstractMechanicalTerm
    basis: AbstractBasis = eqx.field(static=True)
    t: Array
    h: Array
    q0: Array
    p0: Array
    args: Any
    nodes: Array
    weights: Array


def stage_values(basis: AbstractBasis, theta: Array, nodes: Array) -> tuple[Array, Array]:
    """`(q_h(c_j), q_h'(c_j))` at every node, each of shape `(R, D)` (τ-derivative)."""
    return jax.vmap(basis.value_and_derivative, in_axes=(None, 0))(theta, nodes)


def node_momenta_and_forces(ctx: StepContext, q: Array, dq: Array) -> tuple[Array, Array]:
    """`(ϑ_j, f_j)` at the nodes, from stage positions and τ-derivatives."""
    ts = ctx.t + ctx.nodes * ctx.h
    v = dq / ctx.h
    return jax.vmap(ctx.term.momentum_and_force, in_axes=(0, 0, 0, None))(ts, q, v, ctx.args)


def action_gradient(ctx: StepContext, theta: Array) -> Array:
    """`∂A/∂θ` of the discrete action, shape of `θ`."""
    (q, dq), pullback = jax.vjp(lambda th: stage_values(ctx.basis, th, ctx.nodes), theta)
    p, f = node_momenta_and_forces(ctx, q, dq)
    b = ctx.weights[:, None]
    (grad,) = pullback((ctx.h * b * f, b * p))
    return grad


class FreeEndpoints(eqx.Module):
    """Free-endpoint formulation: unknowns `(θ, p_{n+1})`, continuity as an equation."""

    def residual(self, x: tuple[Array, Array], ctx: StepContext) -> tuple[Array, Array]:
        theta, p1 = x
        ends = jnp.array([0.0, 1.0], dtype=theta.dtype)
        (q_ends), pullback = jax.vjp(
            lambda th: jax.vmap(ctx.basis.evaluate, in_axes=(None, 0))(th, ends), theta
        )
        (boundary,) = pullback(jnp.stack([-ctx.p0, p1]))
        r_theta = boundary - action_gradient(ctx, theta)
        r_continuity = ctx.q0 - q_ends[0]
        return r_theta, r_continuity

    def end_state(self, x: tuple[Array, Array], ctx: StepContext) -> tuple[Array, Array]:
        """`(q_{n+1}, p_{n+1})` from the converged unknowns."""
        theta, p1 = x
        return ctx.basis.evaluate(theta, jnp.ones((), theta.dtype)), p1
