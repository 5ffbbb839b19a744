"""The projected step solved without a Jacobian, for a Lagrangian whose kinetic matrix is
constant.

On a span known when the step is traced (`CGVI`, the default network step), the projected
step's equations are linear in the curve's coordinates but for the node values of two
functions of the curve: the forces `f_j = ∂L/∂q` and, where `∂²L/∂v² = M` is constant, the
momentum's offset `g_j = ∂L/∂v − M v_j` (zero for `½ vᵀMv − V(q)`; `A(q)` for a magnetic
term). Given those values the equations are one linear solve with a constant matrix, so the
node values of the curve are fixed linear maps of them:

    Q = q_n + h (h Q_f F + Q_g G + q_p p_nᵀ) M⁻¹,     V = (h V_f F + V_g G + v_p p_nᵀ) M⁻¹,

with `Q_f, Q_g, V_f, V_g` (`R × R`) and `q_p, v_p` (`R`) computed once, in NumPy, when the
step is traced. The fixed-point iteration `F, G ← f, g (Q(F, G), V(F, G))` (Picard's, as in
IRKGL16) then needs one evaluation of the Lagrangian's gradient over all nodes and a few small
products with constants per update: no Jacobian, no factorisation, nothing that depends on the
step but `h`. It contracts at a rate of order `(hω)²` for a motion of frequency `ω`.

It runs until the forces stop changing (round-off), then the step's unknowns
`z = (δc, Δp)` are formed from the last values and the residual of the step's equations is
evaluated once at `z`, as a check. A solve that does not contract (a stiff problem, a long
step) is handed to the root finder's own iteration from the same start (`solve_projected`),
which costs nothing unless some member of a batch needs it.
"""

from __future__ import annotations

from typing import NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .._kinetic_structure import KineticStructure, kinetic_structure
from .._lagrange import continuation_coefficients
from .._linalg import constant_outer, constant_product, elimination_solve, well_conditioned

__all__ = [
    "PicardPlan", "PicardSolve", "extrapolation", "picard_engine", "picard_plan",
    "picard_solve", "newton_solve", "start_at_rest",
]

# Updates made first without any test (their changes are not even measured), then updates
# made without a test in between (they measure the changes that the first test reads), before
# the loop that tests each one: a step that contracts as most do ends without entering it.
PLAIN = 0
UNROLLED = 0
# Updates at most before the iteration is handed to the root finder's own.
MAX_UPDATES = 40
# Stop once the predicted remaining change of the forces is below 1/PREDICT_MARGIN of a
# rounding unit of them (relative to their largest value).
PREDICT_MARGIN = 1024
# A change within NOISE rounding units of the forces is rounding noise: once the changes stop
# shrinking there, the iteration is at round-off.
NOISE = 64
# Consecutive growing updates, above the noise, that end the iteration as not contracting.
MAX_GROWTH = 2


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
    plan = picard_plan(span, ctx.weights)
    if plan is None:
        return None
    structure = kinetic_structure(ctx.term, ctx.t, ctx.q0, ctx.args)
    if structure is None or not structure.mass_constant:
        return None
    if structure.mass is not None and not well_conditioned(structure.mass):
        return None
    return plan, structure, span


class PicardPlan(NamedTuple):
    """The constant maps of the iteration (NumPy float64), for one span and rule: `xf, xg`
    (`(k + 1) × R`), `xp` (`k + 1`) map node values to the unknowns `X = [δc M / h; Δp]`;
    `kinv`, the inverse of the kinetic part of the equations' Jacobian in `X`. The equations
    themselves are the formulation's (`VariableProjection.reduced_residual_and_forces`)."""

    xf: np.ndarray
    xg: np.ndarray
    xp: np.ndarray
    kinv: np.ndarray


def picard_plan(span, weights) -> PicardPlan | None:
    """The `PicardPlan` of a span known when the step is traced and the same in every
    coordinate (`VariableProjection.uniform_span`); `None` where it is not, or where the
    kinetic block of its equations is singular."""
    from .projection import VariableProjection

    if isinstance(weights, jax.core.Tracer) or not VariableProjection.uniform_span(span):
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


class PicardSolve(NamedTuple):
    """How the iteration ended: the unknowns `z = (δc, Δp)`, the node values `(F, G)` it
    ended with (the forces at the nodes of the last curve, and the momentum's offsets), the
    updates made, the residual's size at the last update, whether it converged, how it
    failed where it did not (0: a value not finite, 1: the changes grew, 2: too many
    updates), and the unknowns it started from."""

    unknowns: tuple[Array, Array]
    values: tuple[Array, Array]
    iterations: Array
    residual: Array
    converged: Array
    failure: Array
    start: tuple[Array, Array]

    def result(self):
        """The step's `RESULTS`: successful where it converged, else what ended it."""
        from .._results import STEP_FAILURES

        where = diffrax.RESULTS.where
        ended = where(self.failure == 1, STEP_FAILURES["vi_step_stalled"],
                      STEP_FAILURES["vi_step_max_iterations"])
        ended = where(self.failure == 0, STEP_FAILURES["vi_step_nonfinite"], ended)
        return where(self.converged, diffrax.RESULTS.successful, ended)


class _Carry(NamedTuple):
    """The iteration's state, packed so that an update writes three arrays (each array a
    loop carries is at least one kernel of its own per update, scalars included): the
    unknowns `x = [δc; Δp]` (`(k + 1) × D`), the forces `f` at the nodes, and `stats`, the
    scalars of the stopping rules in the order of `_STATS`, stored in the unknowns' dtype
    (counts and flags are small integers, exact in any float)."""

    x: Array
    f: Array
    stats: Array


_STATS = ("change", "rate", "residual", "growth", "updates", "converged", "done")
_CHANGE, _RATE, _RESIDUAL, _GROWTH, _UPDATES, _CONVERGED, _DONE = range(len(_STATS))


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


def start_at_rest(structure: KineticStructure, ctx) -> tuple[Array, Array]:
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


def picard_solve(plan: PicardPlan, structure: KineticStructure, ctx, span,
                 start: tuple[Array, Array], residual) -> PicardSolve:
    """Solve the step's equations `residual(z) -> ((r, c), f)` (the projected step's reduced
    residual, and the forces at the nodes) by the iteration `z ← z − K⁻¹ (r, c)`, with `K`
    the kinetic part of their Jacobian (constant here), from the unknowns that the node
    values `start = (F, G)` give.

    The iteration is Picard's for the node values: with `K` the whole Jacobian but for the
    forces' and offsets' derivatives, one update moves the curve to where the forces of the
    last curve put it. It is run on the step's own equations, not on the node values, so
    that its fixed point is their root as rounded in this step (constant maps rounded once,
    when the step is traced, would put the same error into every step: an energy drift)."""
    dtype = ctx.q0.dtype
    h, p0 = ctx.h, ctx.p0
    kinetic = _kinetic(structure, ctx)
    k = plan.xf.shape[0] - 1
    live = span.live

    f0, g0 = (a.astype(dtype) for a in start)
    x = (h * constant_product(plan.xf, f0) + constant_product(plan.xg, g0)
         + constant_outer(plan.xp, p0))
    z0 = (jnp.where(live, h * kinetic.times_minv(x[:k]), 0).astype(dtype), x[k].astype(dtype))

    def correction(z, r, cont):
        rows = jnp.concatenate([jnp.where(live, r, 0), kinetic.times_mass(cont[None]) / h])
        dx = -constant_product(plan.kinv, rows)
        return jnp.where(live, h * kinetic.times_minv(dx[:k]), 0), dx[k]

    end = _iterate(z0, f0, residual, correction, UNROLLED, PLAIN)
    return _solved(structure, ctx, span, kinetic, end, g0, z0)


def newton_solve(structure: KineticStructure, ctx, span, start: PicardSolve,
                residual, differentiable) -> PicardSolve:
    """The same equations by Newton's iteration, `z ← z − J(z)⁻¹ (r, c)` with the whole
    Jacobian `J` (forward derivatives of `differentiable`, the same equations written so that
    they have derivatives: `fused=False`), from the Jacobian-free
    iteration's start: for a step that iteration does not contract on (a stiff force at a
    long step). It stops by the same rules, and fails where it does not converge either."""
    z0 = start.start
    f0, g0 = start.values
    _, unravel = ravel_pytree(z0)

    def flat_residual(x):
        return ravel_pytree(differentiable(unravel(x))[0])[0]

    def correction(z, r, cont):
        rhs = ravel_pytree((r, cont))[0]
        jacobian = _columnwise_jacobian(flat_residual, ravel_pytree(z)[0])
        return unravel(-elimination_solve(jacobian, rhs))

    end = _iterate(z0, f0, residual, correction, 0)
    solved = _solved(structure, ctx, span, None, end, g0, z0)
    return solved._replace(iterations=solved.iterations + start.iterations)


def _columnwise_jacobian(fn, x: Array) -> Array:
    """`∂fn/∂x` one column per pass of a loop (a forward derivative along each axis).
    `jax.jacfwd` would batch the derivatives, and XLA's CPU backend compiles the batched
    products of a span of more than a few directions as calls of its dot library, which keep
    the solve's loop from being compiled whole (`linalg.elimination_solve`)."""
    n = x.shape[0]
    out = jax.eval_shape(fn, x)

    def column(i, jacobian):
        _, derivative = jax.jvp(fn, (x,), ((jnp.arange(n) == i).astype(x.dtype),))
        return jax.lax.dynamic_update_slice(jacobian, derivative[:, None], (0, i))

    return jax.lax.fori_loop(0, n, column, jnp.zeros((out.shape[0], n), out.dtype))


def _iterate(z0, f0, residual, correction, unrolled: int, plain: int = 0) -> _Carry:
    """`z ← z + correction(z, r, c)` from `z0` until the change is at round-off (predicted or
    seen), growing, not finite, or `MAX_UPDATES` were made; the first `plain` updates measure
    nothing, the next `unrolled` have no test in between."""
    dtype = z0[1].dtype
    eps = float(jnp.finfo(dtype).eps)
    tiny = float(jnp.finfo(dtype).tiny)
    k = z0[0].shape[0]

    def split(x):
        return x[:k], x[k]

    def update(c: _Carry) -> _Carry:
        z = split(c.x)
        (r, cont), f = residual(z)
        dc, dp = correction(z, r, cont)
        dx = jnp.concatenate([dc, dp[None]])
        x = c.x + dx
        # the three sizes the tests need, in one kernel
        delta, size, fsize = _max_abs(jnp.stack([dx, x, jnp.concatenate([r, cont[None]])]))
        last = c.stats
        change = delta / jnp.maximum(size, tiny)
        known = jnp.isfinite(last[_CHANGE]) & (last[_CHANGE] > 0)
        rate = change / jnp.where(known, last[_CHANGE], 1)
        # the worse of the last two rates: the error has several modes, and a ratio taken as
        # a fast one dies out understates the slow one's (stopping one update early leaves an
        # error of the same sign on every step, an energy drift)
        worst = jnp.maximum(rate, last[_RATE])
        predicted = known & (worst < 1) & (change * worst <= (1 - worst) * eps / PREDICT_MARGIN)
        at_noise = (change <= NOISE * eps) & (change >= 0.5 * last[_CHANGE])
        finite = jnp.isfinite(change)
        converged = ((change == 0) | predicted | at_noise) & finite
        growing = (change > NOISE * eps) & (change >= last[_CHANGE])
        growth = jnp.where(growing, last[_GROWTH] + 1, 0)
        updates = last[_UPDATES] + 1
        done = converged | ~finite | (growth > MAX_GROWTH) | (updates >= MAX_UPDATES)
        # one array, so that the scalars are one fused kernel rather than one each
        stats = jnp.stack([change, jnp.where(known, rate, jnp.inf), fsize, growth, updates,
                           converged, done]).astype(dtype)
        return _Carry(x, f, stats)

    z, f = z0, f0
    for _ in range(plain):
        (r, cont), f = residual(z)
        dc, dp = correction(z, r, cont)
        z = (z[0] + dc, z[1] + dp)
    stats = np.zeros(len(_STATS))
    stats[[_CHANGE, _RATE, _RESIDUAL]] = np.inf
    stats[_UPDATES] = plain
    carry = _Carry(jnp.concatenate([z[0], z[1][None]]), f, jnp.asarray(stats, dtype))
    for _ in range(unrolled):
        carry = update(carry)
    return jax.lax.while_loop(lambda c: c.stats[_DONE] == 0, update, carry)


def _max_abs(x: Array) -> Array:
    """`max |x|` over all axes but the first, by halving elementwise maxima: a reduction of
    these sizes costs far more as a reduction kernel (alone and under `vmap`) than as a
    few fused elementwise operations."""
    a = jnp.abs(x.reshape(x.shape[0], -1))
    while a.shape[1] > 1:
        half = a.shape[1] // 2
        top = jnp.maximum(a[:, :half], a[:, half:2 * half])
        a = top if a.shape[1] % 2 == 0 else jnp.concatenate([top, a[:, 2 * half:]], axis=1)
    return a[:, 0]


def _solved(structure, ctx, span, kinetic: _Kinetic | None, end: _Carry, g0, z0
            ) -> PicardSolve:
    dtype = ctx.q0.dtype
    k = z0[0].shape[0]
    z = (end.x[:k], end.x[k])
    stats = end.stats
    g = g0
    if structure.offset_moves:  # the offsets of the last curve, for the next step's start
        kinetic = kinetic or _kinetic(structure, ctx)
        q, dq = _curve_at_nodes(span, z[0], ctx.q0)
        p, _ = _momenta_and_forces(ctx, q, dq / ctx.h)
        g = p - kinetic.times_mass(dq / ctx.h)
    change = stats[_CHANGE]
    failure = jnp.where(jnp.isfinite(change), jnp.where(stats[_GROWTH] > MAX_GROWTH, 1, 2), 0)
    return PicardSolve(z, (end.f, g), stats[_UPDATES].astype(jnp.int32),
                       stats[_RESIDUAL].astype(dtype), stats[_CONVERGED] != 0, failure, z0)


def _curve_at_nodes(span, dc, q0):
    gq, gv = (np.asarray(a, np.float64)[0] for a in (span.gq, span.gv))
    return q0 + constant_product(gq, dc), constant_product(gv, dc)
