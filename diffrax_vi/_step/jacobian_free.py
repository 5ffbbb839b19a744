"""The projected step's Jacobian-free update, for a Lagrangian whose kinetic matrix is
constant: what the step offers `JacobianFreeIteration` (`diffrax_vi._root_finder`).

On a span known when the step is traced (`CGVI`, the default network step), the projected
step's equations are linear in the curve's coordinates but for the node values of two
functions of the curve: the forces `f_j = ∂L/∂q` and, where `∂²L/∂v² = M` is constant, the
momentum's offset `g_j = ∂L/∂v − M v_j` (zero for `½ vᵀMv − V(q)`; `A(q)` for a magnetic
term). Given those values the equations are one linear solve with a constant matrix, so the
node values of the curve are fixed linear maps of them:

    Q = q_n + h (h Q_f F + Q_g G + q_p p_nᵀ) M⁻¹,     V = (h V_f F + V_g G + v_p p_nᵀ) M⁻¹,

with `Q_f, Q_g, V_f, V_g` (`R × R`) and `q_p, v_p` (`R`) computed once, in NumPy, when the
step is traced. The start of a step's iteration is those maps applied to the last step's
node values continued (`extrapolation`, as IRKGL16 starts its stages); its update is
`z ← z − K⁻¹ (r, c)` with `K` the kinetic part of the equations' Jacobian, constant here
(`EngineUpdate`). The iteration runs on the step's own equations, not on the node values,
so that its fixed point is their root as rounded in this step (constant maps rounded once,
when the step is traced, would put the same error into every step: an energy drift).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._kinetic_structure import KineticStructure, kinetic_structure
from .._lagrange import continuation_coefficients
from .._linalg import constant_outer, constant_product, well_conditioned
from .._precision import two_sum

__all__ = [
    "Engine", "PicardPlan", "end_increments", "end_offsets", "engine_start", "engine_update",
    "extrapolation", "picard_engine", "picard_plan", "start_at_rest",
]


def picard_engine(allowed: bool, formulation, ctx):
    """`(plan, structure, span)` of the Jacobian-free iteration where a step can take it: a
    root finder that allows it (`allowed`), the projected step on a span known when the step
    is traced and the same in every coordinate (a linear ansatz, a fixed hidden layer), and
    a Lagrangian whose kinetic matrix is constant and well conditioned. Decided when the
    step is traced; else `None`."""
    if not allowed:
        return None
    span = formulation.fixed_span(ctx)
    if span is None:
        return None
    plan = picard_plan(span, ctx.weights, formulation.uniform_span(span))
    if plan is None:
        return None
    structure = kinetic_structure(ctx.term, ctx.t, ctx.q0, ctx.args)
    if structure is None or not structure.mass_constant:
        return None
    if structure.mass is not None and not well_conditioned(structure.mass):
        return None
    return Engine(plan, structure, span)


class PicardPlan(NamedTuple):
    """The constant maps of the iteration (NumPy float64), for one span and rule: `xf, xg`
    (`(k + 1) × R`), `xp` (`k + 1`) map node values to the unknowns `X = [δc M / h; Δp]`;
    `kinv`, the inverse of the kinetic part of the equations' Jacobian in `X`. The equations
    themselves are the formulation's (`VariableProjection.reduced_residual_and_forces`)."""

    xf: np.ndarray
    xg: np.ndarray
    xp: np.ndarray
    kinv: np.ndarray


def picard_plan(span, weights, uniform: bool) -> PicardPlan | None:
    """The `PicardPlan` of a span known when the step is traced and the same in every
    coordinate (`uniform`: `VariableProjection.uniform_span`); `None` where it is not, or where the
    kinetic block of its equations is singular."""
    if isinstance(weights, jax.core.Tracer) or not uniform:
        return None
    gq, gv, g0, gd = (np.asarray(a, np.float64)[0] for a in (span.gq, span.gv, span.g0, span.gd))
    live = np.asarray(span.live)[:, 0]
    b = np.asarray(weights, np.float64)
    k = gq.shape[1]
    # Rows of the equations along each live direction, in X = [δc M / h; Δp]:
    #   −Σ_l S_kl X_l + (g0 + gd)_k X_k+1 = h Σ_j b_j gq_jk f_j + Σ_j b_j gv_jk g_j − gd_k p_n,
    # and continuity Σ_k g0_k X_k = 0; a pinned direction has X_k = 0.
    stiff = np.einsum("j,jk,jl->kl", b, gv, gv)
    block = np.zeros((k + 1, k + 1))
    block[:k, :k] = np.where(live[:, None], -stiff, np.eye(k))
    block[:k, k] = np.where(live, g0 + gd, 0.0)
    block[k, :k] = g0
    try:
        inverse = np.linalg.inv(block)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(inverse)):
        return None
    wf = np.where(live[:, None], (b[:, None] * gq).T, 0.0)  # (k, R)
    wg = np.where(live[:, None], (b[:, None] * gv).T, 0.0)
    wp = np.where(live, gd, 0.0)
    xf, xg, xp = inverse[:, :k] @ wf, inverse[:, :k] @ wg, -(inverse[:, :k] @ wp)
    # the residual's continuity row is −Σ_k g0_k δc_k
    jacobian = block.copy()
    jacobian[k, :k] = -g0
    return PicardPlan(xf=xf, xg=xg, xp=xp, kinv=np.linalg.inv(jacobian))


class _Kinetic(NamedTuple):
    """Products with the kinetic matrix and its inverse on the coordinate axis."""

    times_mass: object
    times_minv: object


def _kinetic(structure: KineticStructure, ctx) -> _Kinetic:
    dim = ctx.q0.shape[0]
    if structure.mass is not None:
        mass_np = structure.mass
        if np.array_equal(mass_np, np.eye(dim)):
            return _Kinetic(lambda x: x, lambda x: x)
        minv_np = np.linalg.inv(mass_np)
        return _Kinetic(lambda x: constant_product(mass_np.T, x.T).T,
                        lambda x: constant_product(minv_np.T, x.T).T)
    mass = jax.hessian(lambda v: ctx.term(ctx.t, ctx.q0, v, ctx.args))(jnp.zeros_like(ctx.q0))
    minv = jnp.linalg.inv(mass)
    return _Kinetic(lambda x: x @ mass, lambda x: x @ minv)


def node_times(ctx) -> Array:
    return ctx.t + ctx.nodes.astype(ctx.q0.dtype) * ctx.h


def _momenta_and_forces(ctx, q, v):
    return jax.vmap(ctx.term.momentum_and_force, in_axes=(0, 0, 0, None))(
        node_times(ctx), q, v, ctx.args
    )


def start_at_rest(ctx) -> tuple[Array, Array]:
    """The start of a step with nothing to continue: the forces of the constant curve `q_n`
    at every node (and its momentum offsets)."""
    r = ctx.nodes.shape[0]
    zero = jnp.zeros_like(ctx.q0)
    p, f = ctx.term.momentum_and_force(ctx.t, ctx.q0, zero, ctx.args)
    shape = (r, ctx.q0.shape[0])
    return (jnp.broadcast_to(f.astype(ctx.p0.dtype), shape),
            jnp.broadcast_to(p.astype(ctx.p0.dtype), shape))


def extrapolation(nodes: np.ndarray, ratio: Array, values: Array) -> Array:
    """The polynomial through `values` at `nodes` (`(R, D)`) of the last step, evaluated at
    this step's nodes `1 + ratio·c_j` in the last step's time (`ratio` = this step's length
    over the last's): the next step's start, as IRKGL16 starts its stages."""
    r = len(nodes)
    # ℓ_m(1 + ρ c_i) as a polynomial in ρ, per (i, m): coefficients from NumPy
    coeffs = continuation_coefficients(tuple(float(c) for c in np.asarray(nodes)))
    # the weights as polynomials in ρ (one fused elementwise kernel), then one product; under
    # `vmap` (ρ differs between members) the product is one batched `dot`, so that the
    # weights' kernel is not fused into a slow reduction over the members
    def weights_at(ratio):
        weights = jnp.asarray(coeffs[r - 1], values.dtype)
        for power in range(r - 2, -1, -1):
            weights = weights * ratio + jnp.asarray(coeffs[power], values.dtype)
        return weights

    def alone(ratio, values):
        return jnp.sum(weights_at(ratio)[None, :, :] * values.T[:, None, :], axis=-1).T

    apply = jax.custom_batching.custom_vmap(alone)

    @apply.def_vmap
    def _batched(axis_size, in_batched, ratio, values):
        ratio = ratio if in_batched[0] else jnp.broadcast_to(ratio, (axis_size,))
        values = values if in_batched[1] else jnp.broadcast_to(values, (axis_size, *values.shape))
        weights = jax.vmap(weights_at)(ratio)
        return jnp.einsum("bim,bmd->bid", weights, values), True

    # a start only: nothing of it is differentiated (the layouts have no derivative rule)
    return apply(*jax.lax.stop_gradient((jnp.asarray(ratio, values.dtype), values)))


class Engine(NamedTuple):
    """What the Jacobian-free iteration of one step is built from (`picard_engine`)."""

    plan: PicardPlan
    structure: KineticStructure
    span: object


def engine_start(engine: Engine, ctx, values: tuple[Array, Array]) -> tuple[Array, Array]:
    """The unknowns `z = (δc, Δp)` that the node values `values = (F, G)` give (the curve
    those forces and offsets put the step on)."""
    plan, structure, span = engine
    dtype = ctx.q0.dtype
    f0, g0 = (a.astype(dtype) for a in values)
    x = (ctx.h * constant_product(plan.xf, f0) + constant_product(plan.xg, g0)
         + constant_outer(plan.xp, ctx.p0))
    k = plan.xf.shape[0] - 1
    kinetic = _kinetic(structure, ctx)
    return (jnp.where(span.live, ctx.h * kinetic.times_minv(x[:k]), 0).astype(dtype),
            x[k].astype(dtype))


def engine_update(engine: Engine):
    """`(z, (r, c), args) ↦ −K⁻¹ (r, c)` for the projected step's equations on a span known
    when the step is traced (the hint `update`): `K` is the kinetic part of their Jacobian,
    constant here; the step's context comes in as `args[0]`. A closure over NumPy
    constants, so that they stay constants of the compiled step."""
    kinv, structure = engine.plan.kinv, engine.structure
    live = np.asarray(engine.span.live)
    k = kinv.shape[0] - 1

    def update(z, residual, args):
        del z
        ctx = args[0]
        r, cont = residual
        kinetic = _kinetic(structure, ctx)
        h = ctx.h
        rows = jnp.concatenate([jnp.where(live, r, 0), kinetic.times_mass(cont[None]) / h])
        dx = -constant_product(kinv, rows)
        return jnp.where(live, h * kinetic.times_minv(dx[:k]), 0), dx[k]

    return update


def end_offsets(engine: Engine, ctx, z, offsets: Array) -> Array:
    """The momentum's offsets at the nodes of the curve `z` where they move (else the given
    `offsets`, which are constant), for the next step's start."""
    _, structure, span = engine
    if not structure.offset_moves:
        return offsets
    kinetic = _kinetic(structure, ctx)
    q, dq = _curve_at_nodes(span, z[0], ctx.q0)
    p, _ = _momenta_and_forces(ctx, q, dq / ctx.h)
    return p - kinetic.times_mass(dq / ctx.h)


def end_increments(engine: Engine, ctx, z) -> tuple[Array, Array]:
    """`(q_h(1) − q_n, Δp)` of the solution `z = (δc, Δp)`, the first as `Σ_k gd_k δc_k`
    summed accurately (products and sums without rounding, by error-free transformations,
    then rounded once), with the derivative of the plain sum.

    The plain sum's rounding is not noise: its terms are fixed multiples of the state, larger
    than the sum (they cancel), and their roundings over an orbit do not average out. On the
    oscillator (`CGVI(7)`, h = 0.5) they were an energy drift of about 3e-19 per step whose
    sign and size follow where the orbit's amplitude lies within its binade (each run
    drifting its own way, the mean over runs near zero): `benchmarks.engine_energy_growth`."""
    dc, dp = z
    dtype = ctx.q0.dtype
    gd = np.asarray(engine.span.gd, np.float64).T  # (k, D), a constant of the step
    plain = jnp.einsum("kd,kd->d", jnp.asarray(gd, dtype), dc)
    # Every product exactly as a sum of two (Veltkamp's split and Dekker's product; the
    # constant split in NumPy), all directions at once, then a pairwise tree of error-free
    # sums: a few fused operations whatever the number of directions.
    splitter = float(2 ** ((jnp.finfo(dtype).nmant + 2) // 2) + 1)
    a = gd.astype(dtype)
    scaled = splitter * a
    a_hi = scaled - (scaled - a)
    a_lo = a - a_hi
    b = jax.lax.stop_gradient(dc)
    cut = splitter * b
    b_hi = cut - (cut - b)
    b_lo = b - b_hi
    terms = jnp.asarray(a) * b
    errors = ((a_hi * b_hi - terms) + a_hi * b_lo + a_lo * b_hi) + a_lo * b_lo
    while terms.shape[0] > 1:
        if terms.shape[0] % 2:
            terms, errors = (jnp.concatenate([x, jnp.zeros_like(x[:1])]) for x in (terms, errors))
        terms, rounding = two_sum(terms[0::2], terms[1::2])
        errors = errors[0::2] + errors[1::2] + rounding
    accurate = terms[0] + errors[0]
    dq = plain + jax.lax.stop_gradient(accurate - plain)
    return dq.astype(dtype), dp.astype(ctx.p0.dtype)


def _curve_at_nodes(span, dc, q0):
    gq, gv = (np.asarray(a, np.float64)[0] for a in (span.gq, span.gv))
    return q0 + constant_product(gq, dc), constant_product(gv, dc)
