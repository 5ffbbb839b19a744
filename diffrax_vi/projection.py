"""Variable projection: a well-posed network step.

A shallow network `q_d(τ) = Σ_i α_id σ(w_id τ + β_id)` is linear in its output weights `α`.
The discrete action sees the curve only through `2R + 2` numbers per coordinate (its values and
slopes at the `R` nodes, its two end values), while the network has `3S` parameters per
coordinate: solving for all of them (`FreeEndpoints`) leaves a manifold of roots, and a damped
Newton method stops on a least-squares floor somewhere on it.

`VariableProjection` splits the parameters. The hidden layer `(w, β)` comes from the step's
seed and spans the feature functions `σ(w_i τ + β_i)`; the step then solves the free-endpoint
equations for the curve *in that span*, exactly. Because nearly collinear features make the
span numerically smaller than `S`, it is first orthonormalised in the norm the quadrature sees
(a thin SVD of the weighted data matrix of the features, per coordinate), and only its leading
`k` directions are kept (`k = min(S, R + 1)` by default: a curve space as large as the one of
the classical cGVI of degree `R`, which `R` Gauss nodes determine). The unknowns are then `k`
coefficients per coordinate and `p_{n+1}`: a square system with an isolated root, which plain
Newton solves to round-off in a few iterations (`RoundoffNewton`).

The output weights follow from the coefficients, so the converged step is a network again
(dense output, warm starts and the next step's seed read it as one). Measured at converged
oscillator steps, the hidden-parameter equations of the all-parameter system hold there to
round-off as well: the projected root is one of the roots the all-parameter solve wanders
among, the best-conditioned one.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .ansatz.base import AbstractBasis
from .ansatz.shallow import ShallowNetBasis
from .formulation import FreeEndpoints, StepContext, node_momenta_and_forces, stage_values
from .linalg import solve

__all__ = ["VariableProjection", "ProjectedSpan", "RoundoffNewton"]


def _work_dtype(dtype):
    return jnp.float32 if jnp.finfo(dtype).bits < 32 else dtype


class ProjectedSpan(eqx.Module):
    """The orthonormalised feature span of one step, per coordinate `d`.

    `gq`, `gv` (`(D, R, k)`): values and τ-slopes of the `k` span directions at the nodes;
    `g0`, `g1` (`(D, k)`): their values at `τ = 0` and `τ = 1`; `to_alpha` (`(D, S, k)`): the
    output weights of each direction; `live` (`(k, D)`): directions kept (the others are
    numerically absent from the span and pinned to zero); `hidden`: `(w, β)`, each `(S, D)`.
    """

    gq: Array
    gv: Array
    g0: Array
    g1: Array
    to_alpha: Array
    live: Array
    hidden: tuple[Array, Array]


class VariableProjection(FreeEndpoints):
    """Free endpoints, solved on the span of the seed's hidden layer (variable projection).

    The curve is the network, `q_{n+1} = q_h(1)` and `p_{n+1}` is an unknown, as with
    `FreeEndpoints`; but only the output weights move, within the leading `rank` directions
    of the orthonormalised feature span, and the hidden layer `(w, β)` is the seed's. The
    step's equations are then square with an isolated root. Needs a `ShallowNetBasis`
    without mirrored pairs.

    **Arguments:**

    - `rank`: directions of the feature span kept per coordinate. Default `None`:
      `min(width, R + 1)` for `R` quadrature nodes.
    - `rtol`: a direction whose singular value is below `rtol` times the largest is taken as
      absent and its coefficient pinned to zero. Default `None`: `sqrt(eps)` of the working
      dtype.
    - `reuse_hidden`: keep the hidden layer of the first step's seed for all later steps
      (each step solves on its span, starting from the previous curve continued) instead of
      fitting a seed on every step. Default `False`.
    """

    rank: int | None = eqx.field(static=True, default=None)
    rtol: float | None = eqx.field(static=True, default=None)
    reuse_hidden: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.rank is not None and (
            not isinstance(self.rank, int) or isinstance(self.rank, bool) or self.rank < 1
        ):
            raise ValueError(f"rank must be None or a positive integer, got {self.rank!r}")
        if not isinstance(self.reuse_hidden, bool):
            raise TypeError(f"reuse_hidden must be True or False, got {self.reuse_hidden!r}")
        if self.rtol is not None and not (
            isinstance(self.rtol, int | float) and not isinstance(self.rtol, bool)
            and 0 <= self.rtol < 1
        ):
            raise ValueError(f"rtol must be None or a number in [0, 1), got {self.rtol!r}")

    def check_basis(self, basis: AbstractBasis, num_nodes: int) -> None:
        """Refuse an ansatz the projection cannot split, or a rank above the width."""
        if not isinstance(basis, ShallowNetBasis) or basis.mirrored:
            raise ValueError(
                "VariableProjection() splits a shallow network into hidden layer and output "
                f"weights; it needs a ShallowNetBasis without mirrored pairs, got {basis!r}. "
                "Use FreeEndpoints() for other ansätze."
            )
        if self.rank is not None and self.rank > basis.width:
            raise ValueError(
                f"rank={self.rank} exceeds the network's width {basis.width}: the span of "
                "its features has at most width directions"
            )
        del num_nodes

    def span_rank(self, basis: ShallowNetBasis, num_nodes: int) -> int:
        """`k`: the directions kept per coordinate."""
        if self.rank is not None:
            return self.rank
        return min(basis.width, num_nodes + 1)

    def span(self, theta: Array, ctx: StepContext) -> ProjectedSpan:
        """The orthonormalised span of the hidden layer of `theta` on this step."""
        basis = ctx.basis
        dtype = ctx.q0.dtype
        _, w, beta = basis.split(theta)
        nodes = ctx.nodes.astype(dtype)
        n = nodes.shape[0]
        k = self.span_rank(basis, n)
        taus = jnp.concatenate([nodes, jnp.array([0.0, 1.0], dtype)])
        z = w * taus[:, None, None] + beta  # (K, S, D)
        value, slope = jax.jvp(basis.activation, (z,), (jnp.ones_like(z),))
        slope = w * slope
        root_b = jnp.sqrt(ctx.weights.astype(dtype))[:, None, None]
        data = jnp.concatenate([root_b * value[:n], root_b * slope[:n], value[n:]])
        data = jnp.moveaxis(data, 2, 0)  # (D, 2R + 2, S)
        work = _work_dtype(dtype)
        u, s, vt = jnp.linalg.svd(data.astype(work), full_matrices=False)
        u, s, v = u[..., :k], s[..., :k], jnp.swapaxes(vt, 1, 2)[..., :k]
        rtol = self.rtol if self.rtol is not None else float(jnp.finfo(dtype).eps) ** 0.5
        live = s > rtol * s[..., :1]
        inv = jnp.where(live, 1 / jnp.where(live, s, 1), 0)
        root_b = root_b[:, 0, 0].astype(work)
        span = ProjectedSpan(
            gq=u[:, :n] / root_b[None, :, None],
            gv=u[:, n : 2 * n] / root_b[None, :, None],
            g0=u[:, 2 * n],
            g1=u[:, 2 * n + 1],
            to_alpha=v * inv[:, None, :],
            live=live.T,
            hidden=(w, beta),
        )
        def cast(a):
            return a if a.dtype == jnp.bool_ else a.astype(dtype)

        return jax.lax.stop_gradient(jax.tree_util.tree_map(cast, span))

    def reduce(self, theta: Array, span: ProjectedSpan, ctx: StepContext) -> Array:
        """Coefficients `(k, D)` of the curve of the network `theta` (any hidden layer)
        projected on `span`, by least squares in the quadrature's norm: the Newton start."""
        dtype = ctx.q0.dtype
        b = ctx.weights.astype(dtype)
        q, dq = stage_values(lambda tau: ctx.basis.evaluate(theta, tau), ctx.nodes.astype(dtype))
        ends = jax.vmap(ctx.basis.evaluate, in_axes=(None, 0))(theta, jnp.array([0.0, 1.0], dtype))
        # The span's data columns are orthonormal, so projecting is one product with them.
        c = (
            jnp.einsum("j,djk,jd->kd", b, span.gq, q)
            + jnp.einsum("j,djk,jd->kd", b, span.gv, dq)
            + span.g0.T * ends[0]
            + span.g1.T * ends[1]
        )
        return jnp.where(span.live, c, 0)

    def expand(self, c: Array, span: ProjectedSpan) -> Array:
        """The network parameters `(α, w, β)` whose curve is `Σ_k c_kd (direction k)`."""
        alpha = jnp.einsum("dsk,kd->sd", span.to_alpha, c)
        w, beta = span.hidden
        return ShallowNetBasis.join(alpha, w, beta)

    def reduced_residual(self, z, args) -> tuple[Array, Array]:
        """Free-endpoint equations in the span coordinates `z = (c, p_{n+1})`: the action's
        stationarity along each live direction (`(k, D)`; pinned directions: `c = 0`) and
        continuity `q_h(0) = q_n`."""
        ctx, span = args
        c, p1 = z
        q = jnp.einsum("djk,kd->jd", span.gq, c)
        dq = jnp.einsum("djk,kd->jd", span.gv, c)
        p, f = node_momenta_and_forces(ctx, q, dq)
        b = ctx.weights.astype(c.dtype)
        r = (
            p1 * span.g1.T
            - ctx.p0 * span.g0.T
            - jnp.einsum("j,jd,djk->kd", ctx.h * b, f, span.gq)
            - jnp.einsum("j,jd,djk->kd", b, p, span.gv)
        )
        r = jnp.where(span.live, r, c)
        return r, ctx.q0 - jnp.einsum("dk,kd->d", span.g0, c)

    def reduced_jacobian(self, z, args) -> Array:
        """The Jacobian of `reduced_residual`, dense, in the order of `ravel_pytree`: the
        curve is linear in `c`, so it needs only the Lagrangian's second derivatives at the
        nodes (one `jax.jacfwd` of `(ϑ, f)` per node)."""
        ctx, span = args
        c, _ = z
        dtype = c.dtype
        k, dim = c.shape
        h = ctx.h
        b = ctx.weights.astype(dtype)
        q = jnp.einsum("djk,kd->jd", span.gq, c)
        dq = jnp.einsum("djk,kd->jd", span.gv, c)
        ts = ctx.t + ctx.nodes * h

        def mf(t, qj, vj):
            return ctx.term.momentum_and_force(t, qj, vj, ctx.args)

        (pq, pv), (fq, fv) = jax.vmap(jax.jacfwd(mf, argnums=(1, 2)), in_axes=(0, 0, 0))(
            ts, q, dq / h
        )
        a, bv = span.gq, span.gv
        coupling = (
            jnp.einsum("j,djk,jde,ejl->kdle", h * b, a, fq, a)
            + jnp.einsum("j,djk,jde,ejl->kdle", b, a, fv, bv)
            + jnp.einsum("j,djk,jde,ejl->kdle", b, bv, pq, a)
            + jnp.einsum("j,djk,jde,ejl->kdle", b / h, bv, pv, bv)
        )
        n = k * dim
        eye = jnp.eye(dim, dtype=dtype)
        jcc = -coupling.reshape(n, n)
        live = span.live.reshape(n)
        jcc = jnp.where(live[:, None], jcc, jnp.eye(n, dtype=dtype))
        jcp = jnp.where(live[:, None], jnp.einsum("dk,de->kde", span.g1, eye).reshape(n, dim), 0)
        jpc = -jnp.einsum("dl,de->dle", span.g0, eye).reshape(dim, n)
        top = jnp.concatenate([jcc, jcp], axis=1)
        bottom = jnp.concatenate([jpc, jnp.zeros((dim, dim), dtype)], axis=1)
        return jnp.concatenate([top, bottom], axis=0)

    def projected_end_state(self, z, span: ProjectedSpan) -> tuple[Array, Array]:
        """`(q_{n+1}, p_{n+1})` from the span coordinates (`q_h(1)` from the orthonormal
        directions, without the cancellation of large output weights)."""
        c, p1 = z
        return jnp.einsum("dk,kd->d", span.g1, c), p1


class _NewtonState(eqx.Module):
    f: Array
    step_norm: Array
    previous_norm: Array
    converged: Array
    stagnated: Array


class RoundoffNewton(optx.AbstractRootFinder):
    """Newton's method for a square system with an isolated root, run to round-off.

    Each iteration solves `J d = −F` by LU with a fresh Jacobian (`options["jacobian"]`, a
    function of the unknowns and `args`, where the caller gives one; else `jax.jacfwd`). The
    solve ends as converged when `max|F| ≤ ftol · scale` (`options["scale"]`), or when the
    Newton update stops shrinking (rounding has taken over) with `max|F| ≤ floor · scale`;
    an update that stops shrinking above that is a failure (`nonlinear_divergence`), and so is
    the iteration cap. No tolerance on the unknowns is needed: quadratic convergence reaches
    the floor in a few iterations.

    **Arguments:**

    - `ftol`: residual for immediate convergence, in units of `eps` of the working dtype
      times the residual scale. Default 64.
    - `floor`: largest residual accepted once the updates stop shrinking, in the same units.
      Default 4096.
    - `rtol`, `atol`, `norm`: unused; diffrax reads them off the root finder of an implicit
      solver.
    """

    ftol: float = 64.0
    floor: float = 4096.0
    rtol: float | None = None
    atol: float | None = None
    norm: Callable = optx.max_norm

    def _tolerance(self, name: str, dtype) -> float:
        return getattr(self, name) * float(jnp.finfo(dtype).eps)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del aux_struct, tags, f_struct
        f, _ = fn(y, args)
        flat = ravel_pytree(f)[0]
        inf = jnp.full((), jnp.inf, flat.dtype)
        scale = jnp.asarray(options.get("scale", 1.0), flat.dtype)
        small = jnp.max(jnp.abs(flat)) <= self._tolerance("ftol", flat.dtype) * scale
        return _NewtonState(flat, inf, inf, small, jnp.array(False))

    def step(self, fn, y, args, options, state, tags):
        del tags
        flat_y, unravel = ravel_pytree(y)
        dtype = flat_y.dtype

        def residual(v):
            return ravel_pytree(fn(unravel(v), args)[0])[0]

        given = options.get("jacobian")
        jac = given(y, args) if given is not None else jax.jacfwd(residual)(flat_y)
        d = solve(jac.astype(dtype), -state.f)
        new = flat_y + d
        f, aux = fn(unravel(new), args)
        flat_f = ravel_pytree(f)[0]
        norm = jnp.max(jnp.abs(d))
        scale = jnp.asarray(options.get("scale", 1.0), dtype)
        converged = jnp.max(jnp.abs(flat_f)) <= self._tolerance("ftol", dtype) * scale
        # Rounding has taken over once an update is no smaller than the one before it.
        stagnated = norm >= state.step_norm
        return unravel(new), _NewtonState(flat_f, norm, state.step_norm, converged, stagnated), aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, tags
        dtype = state.f.dtype
        scale = jnp.asarray(options.get("scale", 1.0), dtype)
        fmax = jnp.max(jnp.abs(state.f))
        nonfinite = ~jnp.isfinite(fmax)
        at_floor = state.stagnated & (fmax <= self._tolerance("floor", dtype) * scale)
        failed = nonfinite | (state.stagnated & ~at_floor)
        result = optx.RESULTS.where(
            nonfinite,
            optx.RESULTS.nonfinite,
            optx.RESULTS.where(failed, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful),
        )
        return state.converged | at_floor | failed, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}
