"""Variable projection: the projected network step, a formulation with an isolated root.

A shallow network `q_d(τ) = Σ_i α_id σ(w_id τ + β_id)` is linear in its output weights `α`.
The discrete action sees the curve only through `2R + 2` numbers per coordinate (its values and
slopes at the `R` nodes, its two end values), while the network has `3S` parameters per
coordinate: solving for all of them (`FreeEndpoints`) leaves a manifold of roots, and a damped
Newton method stops on a least-squares floor somewhere on it.

`VariableProjection` splits the parameters. A hidden layer `(w, β)`, chosen by a rule
(`diffrax_vi._hidden_layers`), spans feature functions `σ(w_i τ + β_i)`; the step solves the
free-endpoint equations for the curve in the leading directions of that span
(`diffrax_vi._step.span`, `k = min(S, R + 1)` of them by default: a curve space as large as the one
of the classical cGVI of degree `R`). The unknowns are the curve's change over the step in
these coordinates and `p_{n+1} − p_n`: a square system with an isolated root, which plain
Newton solves to round-off (`RoundoffNewton`). The output weights follow from the
coefficients, so the converged step is a network again (dense output, warm starts and the
next step's seed read it as one).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._activations import numpy_value_and_slope
from .._ansatz.base import AbstractBasis
from .._ansatz.shallow import ShallowNetBasis
from .._hidden_layers import AbstractHiddenLayer, UniformLayer
from .._linalg import constant_product, unpivoted_inverse
from .._precision import lapack_dtype
from .degenerate import first_order_end_correction
from .formulation import (
    CurveSamples,
    FreeEndpoints,
    SolveOptions,
    StepContext,
    StepSolution,
    node_momenta_and_forces,
)
from .projected_solve import solve_projected
from .span import ProjectedSpan, any_traced, feature_span

__all__ = ["KineticInverse", "VariableProjection"]


def _uniform_constants(span: ProjectedSpan):
    """`(gq, gv, g0, gd, live)` as NumPy (`(R, k)`, `(R, k)`, `(k,)`, `(k,)`, `(k,)`) where
    `span` is known when the step is traced and the same in every coordinate
    (`VariableProjection.uniform_span`), else `None`."""
    if not VariableProjection.uniform_span(span):
        return None
    gq, gv, g0, gd = (np.asarray(a, np.float64)[0] for a in (span.gq, span.gv, span.g0, span.gd))
    return gq, gv, g0, gd, np.asarray(span.live)[:, 0]


def _projectable(basis: AbstractBasis) -> bool:
    """A shallow network without mirrored pairs, or a coordinatewise ansatz linear in its
    parameters (an array `(P, D)`)."""
    if isinstance(basis, ShallowNetBasis):
        return not basis.mirrored
    return bool(basis.linear and basis.coordinatewise)


def _features(basis: AbstractBasis) -> int:
    """The features per coordinate: the network's width, or the ansatz's parameters."""
    return basis.width if isinstance(basis, ShallowNetBasis) else basis.num_params()


def _features_at(theta, basis: AbstractBasis, nodes: Array, dim: int, dtype):
    """`(value, slope, hidden)`: the features' values and τ-slopes (`(R + 2, S, D)`) at the
    nodes, then at `τ = 0` and `τ = 1`, and the hidden layer `(w, β)` of a network (`()` for
    a linear ansatz)."""
    taus = jnp.concatenate([jnp.asarray(nodes).astype(dtype), np.array([0.0, 1.0], dtype)])
    if isinstance(basis, ShallowNetBasis):
        _, w, beta = basis.split(theta)
        z = w * taus[:, None, None] + beta  # (K, S, D)
        value, slope = jax.jvp(basis.activation, (z,), (jnp.ones_like(z),))
        return value, w * slope, (w, beta)
    # A linear ansatz: its basis functions are the features, the same in every coordinate
    # (column j of the identity as parameters gives function j).
    eye = np.eye(basis.num_params(), dtype=dtype)
    value, slope = jax.vmap(
        lambda tau: jax.jvp(lambda t: basis.evaluate(eye, t), (tau,), (jnp.ones_like(tau),))
    )(taus)
    return (jnp.repeat(value[:, :, None], dim, axis=2),  # (K, P, D)
            jnp.repeat(slope[:, :, None], dim, axis=2), ())


def _known_features(theta, basis: AbstractBasis, nodes, dim: int, dtype):
    """`_features_at` of inputs known when the step is traced, as NumPy arrays: in NumPy
    where the ansatz has a closed form there (`sample_matrices` of a linear ansatz, a network
    whose activation has `numpy_value_and_slope`), else by one compiled program (operation by
    operation, each would compile on its own), run now (`VariableProjection.span` calls it in
    JAX's eager context, even while a step is being traced)."""
    taus = np.concatenate([np.asarray(nodes, np.float64), [0.0, 1.0]])
    matrices = basis.sample_matrices(taus)
    if matrices is not None:  # closed form in NumPy (`LagrangeBasis`): nothing to compile
        value, slope = matrices
        return (np.repeat(value[:, :, None], dim, axis=2).astype(dtype),
                np.repeat(slope[:, :, None], dim, axis=2).astype(dtype), ())
    numpy_features = _numpy_network_features(theta, basis, taus, dtype)
    if numpy_features is not None:
        return numpy_features
    arrays, static = eqx.partition((theta, basis, nodes), eqx.is_array)
    try:
        hash(static)
        program = _features_program
    except TypeError:  # an ansatz with unhashable settings: compiled for this call
        program = jax.jit(_features_program.__wrapped__, static_argnums=(1, 2, 3))
    out = program(arrays, static, dim, dtype)
    return jax.tree_util.tree_map(np.asarray, out)


def _numpy_network_features(theta, basis: AbstractBasis, taus: np.ndarray, dtype):
    """`_features_at` of a network whose activation has a NumPy form
    (`numpy_value_and_slope`) and whose parameters are known now, in NumPy in the working
    dtype; else `None`."""
    if not isinstance(basis, ShallowNetBasis) or isinstance(theta, jax.core.Tracer):
        return None
    activation = numpy_value_and_slope(basis.activation)
    if activation is None:
        return None
    s = basis.width  # a projectable network has no mirrored pairs: (α, w, β) in blocks
    theta = np.asarray(theta)
    w, beta = theta[s:2 * s], theta[2 * s:]
    z = w * taus.astype(dtype)[:, None, None] + beta  # (K, S, D), promoted as in JAX
    value, slope = activation(z)
    return value, w * slope, (w, beta)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _features_program(arrays, static, dim: int, dtype):
    theta, basis, nodes = eqx.combine(arrays, static)
    return _features_at(theta, basis, nodes, dim, dtype)


class VariableProjection(FreeEndpoints):
    """Free endpoints, solved on the span of the seed's hidden layer (variable projection).

    The curve is the network, `q_{n+1} = q_h(1)` and `p_{n+1}` is an unknown, as with
    `FreeEndpoints`; but only the output weights move, within the leading `rank` directions
    of the orthonormalised feature span of a hidden layer `(w, β)` chosen by `hidden`. The
    step's equations are then square with an isolated root. Needs a `ShallowNetBasis`
    without mirrored pairs.

    **Arguments:**

    - `rank`: directions of the feature span kept per coordinate. Default `None`:
      `min(width, R + 1)` for `R` quadrature nodes.
    - `rtol`: a direction whose singular value is below `rtol` times the largest is taken as
      absent and its coefficient pinned to zero. Default `None`: `eps^(5/8)` of the working
      dtype (1.6e-10 in float64). A kept direction whose singular value is `s` carries about
      `eps/s` of rounding in its data, but a smooth motion needs little of the weak
      directions, and dropping them costs more than their rounding.
    - `hidden`: where the hidden layer comes from: `UniformLayer()` (default; a fixed layer,
      no seed fit), `FirstSeedLayer()` (the first step's seed fit, kept) or `SeedLayer()`
      (each step's seed fit).
    """

    hidden: AbstractHiddenLayer = UniformLayer()
    rank: int | None = eqx.field(static=True, default=None)
    rtol: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.rank is not None and (
            not isinstance(self.rank, int) or isinstance(self.rank, bool) or self.rank < 1
        ):
            raise ValueError(f"rank must be None or a positive integer, got {self.rank!r}")
        if not isinstance(self.hidden, AbstractHiddenLayer):
            raise TypeError(
                "hidden must be UniformLayer(), FirstSeedLayer() or SeedLayer(), got "
                f"{self.hidden!r}"
            )
        if self.rtol is not None and not (
            isinstance(self.rtol, int | float) and not isinstance(self.rtol, bool)
            and 0 <= self.rtol < 1
        ):
            raise ValueError(f"rtol must be None or a number in [0, 1), got {self.rtol!r}")

    def check_basis(self, basis: AbstractBasis) -> None:
        """Refuse an ansatz the projection cannot split, or a rank above the span's size."""
        if not _projectable(basis):
            raise ValueError(
                "VariableProjection() solves for the output weights of a fixed set of "
                "features: it needs a ShallowNetBasis without mirrored pairs (the features of "
                "its hidden layer) or an ansatz linear in its parameters such as LagrangeBasis "
                f"(its basis functions); got {basis!r}. Use FreeEndpoints() for other ansätze."
            )
        if not isinstance(basis, ShallowNetBasis) and not isinstance(self.hidden, UniformLayer):
            raise ValueError(
                f"{basis!r} has no hidden layer to take from a seed: hidden= applies to "
                "networks; leave it at its default for a linear ansatz"
            )
        if self.rank is not None and self.rank > _features(basis):
            raise ValueError(
                f"rank={self.rank} exceeds the {_features(basis)} features of {basis!r}: "
                "the span has at most that many directions"
            )

    def solve_step(self, ctx: StepContext, seed, options: SolveOptions) -> StepSolution:
        """The step's equations on the span of the seed's hidden layer, in increments
        (`diffrax_vi._step.projected_solve`)."""
        hidden, start = seed.start
        return solve_projected(self, ctx, options, hidden, start, seed.restart_history,
                               seed.engine)

    def roots_may_drift(self, basis: AbstractBasis) -> bool:
        del basis
        return False  # a square system with an isolated root

    def fixed_span(self, ctx: StepContext) -> ProjectedSpan | None:
        dim, dtype = ctx.q0.shape[0], ctx.q0.dtype
        with jax.ensure_compile_time_eval():
            hidden = self.hidden.fixed_parameters(ctx.basis, dim, dtype)
        return None if hidden is None else self.span(hidden, ctx)

    def span_rank(self, basis: AbstractBasis, num_nodes: int) -> int:
        """`k`: the directions kept per coordinate."""
        if self.rank is not None:
            return self.rank
        return min(_features(basis), num_nodes + 1)

    def span(self, theta: Array, ctx: StepContext) -> ProjectedSpan:
        """The orthonormalised span of the hidden layer of `theta` on this step.

        Where nothing it depends on is traced (a linear ansatz, or a fixed hidden layer such
        as `UniformLayer`'s), it is computed once, when the step is traced, and enters the
        compiled step as a constant: no factorisation per step."""
        inputs = (theta, ctx.basis, ctx.nodes, ctx.weights, ctx.q0.shape[0], ctx.q0.dtype)
        if not any_traced(*inputs[:4]):
            # NumPy and one compiled program (`_known_features`), run now: concrete arrays
            with jax.core.eval_context():
                return self._span(*inputs)
        with jax.ensure_compile_time_eval():
            return self._span(*inputs)

    def _span(self, theta: Array, basis: AbstractBasis, nodes: Array, weights: Array,
              dim: int, dtype) -> ProjectedSpan:
        # Known when the step is traced (see `feature_span`): the features' values in NumPy
        # or by one compiled program, the rest as `feature_span` computes it.
        known = not any_traced(theta, basis, nodes, weights)
        features = _known_features if known else _features_at
        value, slope, hidden = features(theta, basis, nodes, dim, jnp.dtype(dtype))
        k = self.span_rank(basis, nodes.shape[0])
        rtol = self.rtol if self.rtol is not None else float(jnp.finfo(dtype).eps) ** 0.625
        span = feature_span(value, slope, weights, k, rtol, hidden)
        return span if known else jax.lax.stop_gradient(span)

    def reduce(self, curve: Callable[[Array], Array] | CurveSamples, span: ProjectedSpan,
               ctx: StepContext) -> Array:
        """Coefficients `(k, D)` of a curve `τ ↦ q(τ)` (e.g. a network with any hidden layer,
        or its `CurveSamples`) on `span`, by least squares in the quadrature's norm (the
        directions are orthogonal in it, so each coefficient is one inner product)."""
        dtype = ctx.q0.dtype
        b = ctx.weights.astype(dtype)
        q, dq, ends = CurveSamples.of(curve, ctx.nodes.astype(dtype))
        g1 = span.g1

        def inner(q, dq, e0, e1):
            return (jnp.einsum("j,djk,jd->kd", b, span.gq, q)
                    + jnp.einsum("j,djk,jd->kd", b, span.gv, dq)
                    + span.g0.T * e0 + g1.T * e1)

        norms = (jnp.einsum("j,djk->kd", b, span.gq**2) + jnp.einsum("j,djk->kd", b, span.gv**2)
                 + span.g0.T**2 + g1.T**2)
        c = inner(q, dq, ends[0], ends[1]) / jnp.where(span.live, norms, 1)
        return jnp.where(span.live, c, 0)

    def start(self, curve: Callable[[Array], Array] | CurveSamples, p1: Array,
              span: ProjectedSpan, ctx: StepContext) -> tuple[Array, Array]:
        """The unknowns `z = (δc, p_{n+1} − p_n)` of the curve `curve` (or its samples) and
        the end momentum `p1`: the Newton start."""
        if isinstance(curve, CurveSamples):
            moved = curve._replace(values=curve.values - ctx.q0, ends=curve.ends - ctx.q0)
        else:
            def moved(tau):
                return curve(tau) - ctx.q0
        dc = self.reduce(moved, span, ctx)
        return dc, (p1 - ctx.p0).astype(ctx.p0.dtype)

    def coefficients(self, dc: Array, ctx: StepContext) -> Array:
        """The span coordinates `(k, D)` of the curve `q_n + Σ_k δc_k g_k` (the constant
        direction 0 takes `q_n`)."""
        return dc.at[0].add(ctx.q0)

    def expand(self, c: Array, span: ProjectedSpan) -> Array:
        """The parameters whose curve is `Σ_k c_kd (direction k)`: the network's `(α, w, β)`,
        or a linear ansatz's coefficients."""
        alpha = jnp.einsum("dsk,kd->sd", span.to_alpha, c)
        if not span.hidden:
            return alpha
        w, beta = span.hidden
        return ShallowNetBasis.join(alpha, w, beta)

    @staticmethod
    def node_values(dc: Array, span: ProjectedSpan, q0: Array) -> tuple[Array, Array]:
        """Values and τ-slopes `(R, D)` at the nodes of the curve `q_n + Σ_k δc_k g_k`."""
        if dc.shape[1] == 1:
            q = q0 + jnp.einsum("djk,kd->jd", span.gq, dc)
            dq = jnp.einsum("djk,kd->jd", span.gv, dc)
            return q, dq
        # both as one batched product (fewer kernels; the same values)
        both = jax.vmap(functools.partial(jnp.einsum, "djk,kd->jd"), in_axes=(0, None))(
            jnp.stack([span.gq, span.gv]), dc
        )
        return q0 + both[0], both[1]

    def reduced_residual(self, z, args) -> tuple[Array, Array]:
        """Free-endpoint equations in the span's increment coordinates
        `z = (δc, Δp = p_{n+1} − p_n)`: the action's stationarity along each live direction
        (`(k, D)`; pinned directions: `δc = 0`) and continuity `q_h(0) = q_n`. Along the
        constant direction the equation is `Δp = h Σ_j b_j f_j`, so `Δp` is solved to the
        rounding of its own size."""
        return self.reduced_residual_and_forces(z, args)[0]

    def reduced_residual_and_forces(self, z, args, fused: bool = False
                                    ) -> tuple[tuple[Array, Array], Array]:
        """`reduced_residual` and the forces `∂L/∂q` at the nodes (`(R, D)`) it evaluated
        on the way: the step's dense output reads them at the converged `z`.

        On a span known when the step is traced and the same in every coordinate, its
        products are with constant matrices (`linalg.constant_product`; `fused` lays them
        out for a loop that is not differentiated, as the Jacobian-free iteration's); else
        with the span's arrays. The rule's weights multiply the node values, not the
        span's constants: those must be the very numbers that placed the curve, or the
        equations are no longer the exact stationarity of one discrete action (a fixed
        rounding of `b·gq` would be a drift, not noise)."""
        ctx, span = args[0], args[1]
        dc, dp = z
        dtype = dc.dtype
        h = ctx.h
        b = ctx.weights.astype(dtype)[:, None]
        uniform = _uniform_constants(span)
        if uniform is not None:
            gq, gv, g0, gd, live = uniform
            r_nodes = gq.shape[0]
            # values, slopes and −g0·δc as one product; the weighted sums as another
            curve = constant_product(np.concatenate([gq, gv, -g0[None]]), dc, fused)
            q, dq, c = ctx.q0 + curve[:r_nodes], curve[r_nodes:2 * r_nodes], curve[2 * r_nodes]
        else:
            q, dq = self.node_values(dc, span, ctx.q0)
            c = -jnp.einsum("dk,kd->d", span.g0, dc)
        p, f = node_momenta_and_forces(ctx, q, dq)
        if uniform is not None:
            sums = constant_product(np.concatenate([gq, gv]).T,
                                    jnp.concatenate([(h * b) * f, b * p.astype(dtype)]), fused)
            g0, gd = (jnp.asarray(a, dtype)[:, None] for a in (g0, gd))
            live = jnp.asarray(live)[:, None]
        else:
            b = b[:, 0]
            if dc.shape[1] == 1:
                forces = jnp.einsum("j,jd,djk->kd", h * b, f, span.gq)
                momenta = jnp.einsum("j,jd,djk->kd", b, p, span.gv)
            else:  # both as one batched product (fewer kernels; the same values)
                forces, momenta = jax.vmap(functools.partial(jnp.einsum, "j,jd,djk->kd"))(
                    jnp.stack([h * b, b]), jnp.stack([f, p]), jnp.stack([span.gq, span.gv]))
            sums = forces + momenta
            g0, gd, live = span.g0.T, span.gd.T, span.live
        # p_{n+1} g1 − p_n g0 with g1 = g0 + gd, p_{n+1} = p_n + Δp, term by term
        r = dp * g0 + dp * gd + ctx.p0 * gd - sums
        return (jnp.where(live, r, dc), c), f

    def _at_nodes(self, z, args):
        """What the Jacobians of the reduced residual start from: the step context, the
        span, the coefficients `δc`, the rule's weights in their dtype, and the curve's
        values, slopes and times at the nodes."""
        ctx, span = args[0], args[1]
        dc, _ = z
        q, dq = self.node_values(dc, span, ctx.q0)
        return ctx, span, dc, ctx.weights.astype(dc.dtype), q, dq, ctx.t + ctx.nodes * ctx.h

    def reduced_jacobian(self, z, args) -> Array:
        """The Jacobian of `reduced_residual`, dense, in the order of `ravel_pytree`: the
        curve is linear in `δc`, so it needs only the Lagrangian's second derivatives at the
        nodes (one `jax.jacfwd` of `(ϑ, f)` per node)."""
        ctx, span, dc, b, q, dq, ts = self._at_nodes(z, args)
        dtype, dim, h = dc.dtype, dc.shape[1], ctx.h

        def mf(t, qj, vj):
            return ctx.term.momentum_and_force(t, qj, vj, ctx.args)

        (pq, pv), (fq, fv) = jax.vmap(jax.jacfwd(mf, argnums=(1, 2)), in_axes=(0, 0, 0))(
            ts, q, dq / h
        )
        a, bv = span.gq, span.gv
        weights = (h * b, b, b, b / h)
        hessians = (fq, fv, pq, pv)
        if dim > 1 and self.uniform_span(span):
            # The same directions in every coordinate: the span's part of each block is a
            # constant `(R, k, k)` array, and the coupling one product of the stacked
            # constants with the stacked weighted Hessians (one kernel).
            a0, v0 = (np.asarray(x, np.float64)[0] for x in (a, bv))
            spans = np.concatenate([np.einsum("jk,jl->jkl", x, y)
                                    for x, y in ((a0, a0), (a0, v0), (v0, a0), (v0, v0))])
            weighted = jnp.concatenate([w[:, None, None] * m for w, m in zip(weights, hessians,
                                                                              strict=True)])
            coupling = jnp.einsum("jkl,jde->kdle", jnp.asarray(spans, dtype), weighted)
            return self._assemble(coupling, span, dtype)
        blocks = tuple(zip(weights, (a, a, bv, bv), hessians, (a, bv, a, bv), strict=True))
        contract = functools.partial(jnp.einsum, "j,djk,jde,ejl->kdle")
        if dim == 1:  # plain products, which XLA fuses (and drops where a block is zero)
            terms = [contract(*block) for block in blocks]
        else:
            # The four contractions as one batched one: a few kernels instead of four sets
            # of them, with the same values.
            parts = zip(*blocks, strict=True)
            stacked = jax.vmap(contract)(*(jnp.stack(part) for part in parts))
            terms = list(stacked)
        coupling = terms[0] + terms[1] + terms[2] + terms[3]
        return self._assemble(coupling, span, dtype)

    def reduced_inverse(self, z, args) -> Array:
        """The inverse of `reduced_jacobian`, by elimination without pivoting
        (`unpivoted_inverse`) in a fixed row order: each continuity row takes the place of the
        constant direction's action row (whose diagonal entry is of order `h`, zero for a
        free particle), which takes the place of the continuity row (its entry in the `Δp`
        column is 1). The rest of the diagonal is the kinetic block, of order `M/h`. Non-finite
        where a pivot vanished; the caller falls back to a pivoted factorisation."""
        return self.invert_reduced_jacobian(self.reduced_jacobian(z, args), z)

    @staticmethod
    def invert_reduced_jacobian(jacobian: Array, z) -> Array:
        """`reduced_inverse` of a Jacobian already formed at `z` (the root finder's hint
        `inverse`: the step's program then holds one Jacobian, which the pivoted fallback
        reuses)."""
        k, dim = z[0].shape
        n = k * dim
        order = np.arange(n + dim)
        order[:dim], order[n:] = np.arange(n, n + dim), np.arange(dim)
        return unpivoted_inverse(jacobian, order)

    @staticmethod
    def _assemble(coupling: Array, span: ProjectedSpan, dtype) -> Array:
        """The dense Jacobian of the step's equations from the coupling of the curve's
        coordinates (`(k, D, k, D)`, the action's second derivative), in the order of
        `ravel_pytree`: pinned directions get identity rows, `Δp` enters through `g₁`, and
        continuity through `−g₀`."""
        k, dim = coupling.shape[:2]
        n = k * dim
        eye = jnp.eye(dim, dtype=dtype)
        live = span.live.reshape(n)
        jcc = jnp.where(live[:, None], -coupling.reshape(n, n), jnp.eye(n, dtype=dtype))
        jcp = jnp.where(live[:, None], jnp.einsum("dk,de->kde", span.g1, eye).reshape(n, dim), 0)
        jpc = -jnp.einsum("dl,de->dle", span.g0, eye).reshape(dim, n)
        top = jnp.concatenate([jcc, jcp], axis=1)
        bottom = jnp.concatenate([jpc, jnp.zeros((dim, dim), dtype)], axis=1)
        return jnp.concatenate([top, bottom], axis=0)

    @staticmethod
    def uniform_span(span: ProjectedSpan) -> bool:
        """Whether `span` is known, when the step is traced, to be the same in every
        coordinate (a linear ansatz, or one fixed hidden layer such as `UniformLayer`'s):
        then the kinetic part of the Jacobian is a Kronecker product (`kinetic_inverse`)."""
        leaves = (span.gq, span.gv, span.g0, span.gd, span.live)
        if any(isinstance(a, jax.core.Tracer) for a in leaves):
            return False
        return all(bool(np.all(np.asarray(a) == np.asarray(a)[:1])) for a in leaves)

    def kinetic_inverse(self, z, args, *, uniform: bool = False) -> KineticInverse:
        """The inverse of the kinetic part of `reduced_jacobian` at `z`: the Jacobian of a
        Lagrangian `½ vᵀ M v` with `M` the mass matrix `∂²L/∂v²` averaged over the nodes
        (weighted by the rule), forces and the variation of `M` left out. It is what
        `ChordIteration(matrix="kinetic")` applies: the iteration then contracts at a
        rate of order `(hω)²` for a motion of frequency `ω`, and needs no Jacobian of the
        forces. With `uniform` (`uniform_span`), the system is `A ⊗ M`-structured and the
        inverse costs one `(k + 1)`-square and one `D`-square inverse; otherwise it is formed
        densely."""
        ctx, span, dc, b, q, dq, ts = self._at_nodes(z, args)
        dtype, k, h = dc.dtype, dc.shape[0], ctx.h

        def momentum(t, qj, vj):
            return ctx.term.momentum_and_force(t, qj, vj, ctx.args)[0]

        pv = jax.vmap(jax.jacfwd(momentum, argnums=2))(ts, q, dq / h)
        work = lapack_dtype(dtype)  # inverses in float32 below 32 bits
        mass = jnp.einsum("j,jde->de", b, pv).astype(work)
        b, h = b.astype(work), h.astype(work)
        span = jax.tree_util.tree_map(
            lambda a: a if a.dtype == jnp.bool_ else a.astype(work), span
        )
        dtype = work
        if uniform:
            gv, g0, g1, live = span.gv[0], span.g0[0], span.g1[0], span.live[:, 0]
            stiff = -jnp.einsum("j,jk,jl->kl", b / h, gv, gv)
            stiff = jnp.where(live[:, None], stiff, jnp.eye(k, dtype=dtype))
            top = jnp.concatenate([stiff, jnp.where(live, g1, 0)[:, None]], axis=1)
            bottom = jnp.concatenate([-g0, jnp.zeros((1,), dtype)])[None]
            block = jnp.concatenate([top, bottom], axis=0)
            return KineticInverse(jnp.linalg.inv(block), mass, jnp.linalg.inv(mass))
        coupling = jnp.einsum("j,djk,de,ejl->kdle", b / h, span.gv, mass, span.gv)
        return KineticInverse(jnp.linalg.inv(self._assemble(coupling, span, dtype)))

    def dense_position(self, basis, theta, q0, q1, tau):
        """The network curve plus linear terms that make it hit `q_n` at `τ = 0` and
        `q_{n+1}` at `τ = 1` (which the end correction of a first-order Lagrangian moves)."""
        ends = jnp.array([0.0, 1.0], q0.dtype)
        at_ends = jax.vmap(basis.evaluate, in_axes=(None, 0))(theta, ends)
        q = basis.evaluate(theta, tau) + (1 - tau) * (q0 - at_ends[0]) + tau * (q1 - at_ends[1])
        # exactly the step's ends there (the sum above is only within rounding of them), with
        # the curve's derivative (`q - stop_gradient(q)` is an exact zero)
        exact = jax.lax.stop_gradient(jnp.where(tau == 0, q0, jnp.where(tau == 1, q1, q)))
        return exact + (q - jax.lax.stop_gradient(q))

    def projected_increments(self, z, span: ProjectedSpan, ctx: StepContext
                             ) -> tuple[Array, Array]:
        """`(q_h(1) − q_n, p_{n+1} − p_n)` of the solution `z`, each to the rounding of its
        own size (not of `|q_n|` or `|p_n|`)."""
        dc, dp = z
        dq = jnp.einsum("dk,kd->d", span.gd, dc).astype(ctx.q0.dtype)
        return dq, dp.astype(ctx.p0.dtype)

    def projected_end_state(self, z, span: ProjectedSpan, ctx: StepContext
                            ) -> tuple[Array, Array]:
        """`(q_{n+1}, p_{n+1})` of the solution `z`: the step's start plus its increments,
        summed without compensation; a Lagrangian linear in the velocities also gets
        `q_{n+1}` moved onto its primary constraint `ϑ(q_{n+1}) = p_{n+1}`
        (`first_order_end_correction`)."""
        dq, dp = self.projected_increments(z, span, ctx)
        q1, p1 = ctx.q0 + dq, ctx.p0 + dp
        return q1 + first_order_end_correction(ctx, q1, p1), p1


class KineticInverse(eqx.Module):
    """The inverse of the kinetic part of a projected step's Jacobian
    (`VariableProjection.kinetic_inverse`), applied to a residual `(r, c)` (`(k, D)`, `(D,)`)
    by calling it.

    For a span that is the same in every coordinate the kinetic Jacobian is
    `[[S ⊗ M, g₁ ⊗ I], [−g₀ᵀ ⊗ I, 0]]`; multiplying its first rows by `M⁻¹` and writing
    `Δp = M Δp'` turns it into `A ⊗ I` with the small `A = [[S, g₁], [−g₀ᵀ, 0]]`: then `block`
    holds `A⁻¹` and `mass`, `mass_inv` hold `M` and `M⁻¹`. Otherwise `block` is the dense
    inverse (in the order of `ravel_pytree`) and the other two are `None`."""

    block: Array
    mass: Array | None = None
    mass_inv: Array | None = None

    def __call__(self, f: tuple[Array, Array]) -> tuple[Array, Array]:
        r, c = (x.astype(self.block.dtype) for x in f)
        if self.mass is not None:
            rhs = jnp.concatenate([r @ self.mass_inv.T, c[None]], axis=0)
            out = self.block @ rhs
            return out[:-1], out[-1] @ self.mass.T
        k, dim = r.shape
        out = self.block @ jnp.concatenate([r.reshape(-1), c])
        return out[: k * dim].reshape(k, dim), out[k * dim :]
