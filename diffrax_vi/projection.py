"""Variable projection: a well-posed network step.

A shallow network `q_d(τ) = Σ_i α_id σ(w_id τ + β_id)` is linear in its output weights `α`.
The discrete action sees the curve only through `2R + 2` numbers per coordinate (its values and
slopes at the `R` nodes, its two end values), while the network has `3S` parameters per
coordinate: solving for all of them (`FreeEndpoints`) leaves a manifold of roots, and a damped
Newton method stops on a least-squares floor somewhere on it.

`VariableProjection` splits the parameters. A hidden layer `(w, β)`, chosen by a rule
(`UniformLayer`, the default, is fixed; `FirstSeedLayer` and `SeedLayer` take the seed fit's),
spans the feature functions `σ(w_i τ + β_i)`; the step then solves the free-endpoint equations
for the curve *in that span*, exactly. Because nearly collinear features make the span
numerically smaller than `S`, it is first orthonormalised in the norm the quadrature sees (a
thin SVD of the weighted data matrix of the features, per coordinate), and only its leading
`k` directions are kept (`k = min(S, R + 1)` by default: a curve space as large as the one of
the classical cGVI of degree `R`, which `R` Gauss nodes determine). One of them is the
constant function, exactly (`feature_span`). The unknowns are the curve's change over the
step in these coordinates, `k` per coordinate, and `p_{n+1} − p_n`: a square system with an
isolated root, which plain Newton solves to round-off in a few iterations (`RoundoffNewton`),
and whose increments keep the digits that the state's size would round away (the solver adds
them by compensated summation).

The output weights follow from the coefficients, so the converged step is a network again
(dense output, warm starts and the next step's seed read it as one; the constant direction
through the features' fit of the constant). Measured at converged oscillator steps, the
hidden-parameter equations of the all-parameter system hold there to round-off as well: the
projected root is a root of the all-parameter system, along which the hidden layer is free.
The accuracy of the step is the accuracy of the span.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .activations import ReLUk, gelu, gelu_exact, sigmoid, tanh
from .ansatz.base import AbstractBasis
from .ansatz.shallow import ShallowNetBasis
from .degenerate import first_order_end_correction
from .formulation import FreeEndpoints, StepContext, node_momenta_and_forces, stage_values
from .lazy import unless_all_skip
from .linalg import solve, unpivoted_inverse
from .precision import lapack_dtype
from .step_hints import AbstractStepRootFinder, StepHints, hints_of

__all__ = [
    "AbstractHiddenLayer",
    "FirstSeedLayer",
    "KineticInverse",
    "ProjectedSpan",
    "RoundoffNewton",
    "SeedLayer",
    "UniformLayer",
    "VariableProjection",
    "feature_span",
]


def _projectable(basis: AbstractBasis) -> bool:
    """A shallow network without mirrored pairs, or a coordinatewise ansatz linear in its
    parameters (an array `(P, D)`)."""
    if isinstance(basis, ShallowNetBasis):
        return not basis.mirrored
    return bool(basis.linear and basis.coordinatewise)


def _features(basis: AbstractBasis) -> int:
    """The features per coordinate: the network's width, or the ansatz's parameters."""
    return basis.width if isinstance(basis, ShallowNetBasis) else basis.num_params()


class ProjectedSpan(eqx.Module):
    """The feature span of one step, per coordinate `d`, in coordinates orthogonal in the
    quadrature's norm: direction 0 is the constant function exactly (value 1, slope 0), the
    others are orthonormal and orthogonal to it.

    `gq`, `gv` (`(D, R, k)`): values and τ-slopes of the `k` directions at the nodes; `g0`
    (`(D, k)`): their values at `τ = 0`, `gd` (`(D, k)`): their changes over the step
    (the value at `τ = 1` is `g0 + gd`, never rounded into one number, so that the step's
    equations use the same coefficients everywhere); `to_alpha` (`(D, S, k)`): the output
    weights of each direction; `live` (`(k, D)`): directions kept (the others are
    numerically absent from the span and pinned to zero); `hidden`: `(w, β)`, each `(S, D)`,
    for a network, `()` for a linear ansatz.
    """

    gq: Array
    gv: Array
    g0: Array
    gd: Array
    to_alpha: Array
    live: Array
    hidden: tuple[Array, Array] | tuple[()]

    @property
    def g1(self) -> Array:
        """The directions' values at `τ = 1` (rounded; the step itself uses `g0` and `gd`)."""
        return self.g0 + self.gd


def feature_span(value: Array, slope: Array, weights: Array, rank: int, rtol: float,
                 hidden: tuple[Array, Array] | tuple[()] = ()) -> ProjectedSpan:
    """The span of features with values `value` and τ-slopes `slope` (`(R + 2, S, D)`, at the
    `R` nodes of a rule with `weights`, then at `τ = 0` and `τ = 1`): the constant function
    and the `rank − 1` leading directions of the features with the constant projected out
    (thin SVD of their data in the quadrature's norm, per coordinate; a direction whose
    singular value is below `rtol` times the largest of the features is not live).

    The constant is a direction of its own, exactly, so that the curve `q_n + Σ_k δc_k g_k`
    holds every constant whatever the features' rounding: its increment coordinates `δc`
    then keep the digits of the step's change that coefficients of size `|q_n|` would round
    away, and the step is the Galerkin step of a space with the constants (the variation
    that moves `q_n` is in it, so the map stays symplectic in floating point). Its output
    weights are the features' least-squares fit of the constant.

    Where none of its inputs is traced (a span known when the step is traced), it runs in
    NumPy but for its SVDs and contractions, which JAX runs (`_eager_reduction`): the same
    span to the bit as JAX's operations one by one, without compiling each of them."""
    known = not _traced(value, slope, weights, hidden)
    xp = np if known else jnp
    reduce = _eager_reduction if known else _call
    n = value.shape[0] - 2
    dtype = value.dtype
    work = lapack_dtype(dtype)
    root_b = xp.sqrt(xp.asarray(weights).astype(work))
    rb = root_b[:, None, None]
    data = xp.concatenate([rb * value[:n].astype(work), rb * slope[:n].astype(work),
                           value[n:].astype(work)])
    data = xp.moveaxis(data, 2, 0)  # (D, 2R + 2, S)
    dim = data.shape[0]
    one = xp.concatenate([root_b, xp.zeros(n, work), xp.ones(2, work)])  # the constant
    svd = functools.partial(jnp.linalg.svd, full_matrices=False)
    # The constant's output weights: least squares on the features.
    u_a, s_a, vt_a = reduce(svd, data)
    top = s_a[..., :1]
    keep = s_a > rtol * top
    inv_a = xp.where(keep, 1 / xp.where(keep, s_a, 1), 0)
    alpha_one = reduce(functools.partial(jnp.einsum, "dks,dk->ds"), vt_a,
                       inv_a * reduce(functools.partial(jnp.einsum, "dik,i->dk"), u_a, one))
    # The features with the constant projected out, orthonormalised.
    # Divisions by a broadcast value are written as XLA computes them (times the
    # reciprocal), so that the NumPy path rounds alike.
    per_norm2 = 1 / reduce(jnp.dot, one, one)
    along = reduce(functools.partial(jnp.einsum, "i,dis->ds"), one, data) * per_norm2  # (D, S)
    rest = data - one[None, :, None] * along[:, None, :]
    u, s, vt = reduce(svd, rest)
    m = rank - 1
    u, s, v = u[..., :m], s[..., :m], xp.swapaxes(vt, 1, 2)[..., :m]
    live = s > rtol * top
    inv = xp.where(live, 1 / xp.where(live, s, 1), 0)
    # Direction k is `features·w_k − (along·w_k)·1`; the weak ones are orthogonal to the
    # constant only to eps/s_k, so it is projected out once more (`γ_k` of the constant).
    gamma = reduce(functools.partial(jnp.einsum, "i,dik->dk"), one, u) * per_norm2
    u = u - one[None, :, None] * gamma[:, None, :]
    weights_rest = v * inv[:, None, :]  # (D, S, m)
    shift = reduce(functools.partial(jnp.einsum, "ds,dsk->dk"), along, weights_rest) + gamma
    to_alpha = xp.concatenate(
        [alpha_one[:, :, None], weights_rest - alpha_one[:, :, None] * shift[:, None, :]],
        axis=2,
    )
    ones = xp.ones((dim, n, 1), work)
    per_root_b = (1 / root_b)[None, :, None]
    span = ProjectedSpan(
        gq=xp.concatenate([ones, u[:, :n] * per_root_b], axis=2),
        gv=xp.concatenate([0 * ones, u[:, n : 2 * n] * per_root_b], axis=2),
        g0=xp.concatenate([ones[:, 0], u[:, 2 * n]], axis=1),
        gd=xp.concatenate([0 * ones[:, 0], u[:, 2 * n + 1] - u[:, 2 * n]], axis=1),
        to_alpha=to_alpha,
        live=xp.concatenate([xp.ones((dim, 1), bool), live], axis=1).T,
        hidden=hidden,
    )

    def cast(a):
        a = np.asarray(a) if known else a
        a = a if a.dtype == jnp.bool_ else a.astype(dtype)
        return jax.device_put(a) if known else a  # (a transfer; `jnp.asarray` compiles)

    return jax.tree_util.tree_map(cast, span)


def _traced(*trees) -> bool:
    """Whether any leaf of `trees` is traced (else all are known when the step is traced)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(trees))


def _call(fn, *args):
    return fn(*args)


def _as_is(a):
    return a


def _eager_reduction(fn, *args):
    """`fn(*args)` (an SVD or a contraction) run now by JAX, as NumPy arrays.

    A span known when the step is traced is computed then, once. Evaluated by JAX operation
    by operation, each operation is compiled on its own (some 80 of them, seconds of a
    first call). Only its reductions need JAX for that: its other operations (elementwise
    IEEE arithmetic, data movement) round alike in NumPy, which compiles nothing, so the
    span is the same to the bit."""
    with jax.ensure_compile_time_eval():
        return jax.tree_util.tree_map(np.asarray, fn(*args))


class AbstractHiddenLayer(eqx.Module):
    """Where a projected step's hidden layer `(w, β)` comes from."""


class SeedLayer(AbstractHiddenLayer):
    """The hidden layer of each step's own seed (the OGA fit of the trajectory seed, or
    whichever `initial_guess` the solver has): a fit on every step."""


class FirstSeedLayer(AbstractHiddenLayer):
    """The hidden layer of the first step's seed, kept for every later step; each later step
    starts from the previous step's curve continued, so only the first step fits a seed."""


class UniformLayer(AbstractHiddenLayer):
    """A fixed hidden layer in the step's local time: neuron `i` of `S` has weight
    `±scale` (alternating signs) and is centred (`w τ + β = 0`) at `τ_i`, the centres spread
    uniformly over `centres` (for `relu_k`, the neurons centred outside the step face it). The
    same layer on every step and in every coordinate, so the step needs no seed fit and its
    result is a continuous function of the state. Designed for the activations of `suits`:
    with equal `|w|`, periodic units span two functions only, and `elu` or `relu_k(1)` little
    more than the linear ones.

    **Arguments:**

    - `scale`: `|w|` of every neuron. Default 0.5.
    - `centres`: the interval `(a, b)` the centres spread over, in units of the step.
      Default `(-4.0, 5.0)`: centres well outside the step make the features smooth on it,
      so that their span holds the low-degree polynomials a smooth motion needs.
    """

    scale: float = eqx.field(static=True, default=0.5)
    centres: tuple[float, float] = eqx.field(static=True, default=(-4.0, 5.0))

    def __check_init__(self):
        if not (isinstance(self.scale, int | float) and not isinstance(self.scale, bool)
                and self.scale > 0 and math.isfinite(self.scale)):
            raise ValueError(f"scale must be a positive number, got {self.scale!r}")
        pair = isinstance(self.centres, tuple) and len(self.centres) == 2 and all(
            isinstance(c, int | float) and not isinstance(c, bool) for c in self.centres
        )
        if not (pair and all(map(math.isfinite, self.centres))
                and self.centres[0] < self.centres[1]):
            raise ValueError(f"centres must be a finite increasing pair, got {self.centres!r}")

    @staticmethod
    def suits(activation) -> bool:
        """Whether the layer's features span a rich enough space on a step for `activation`
        (`tanh`, `sigmoid`, `gelu`, `gelu_exact`, `relu_k` with `k >= 2`; JAX's own names
        for them are recognised by `ShallowNetBasis`, not here)."""
        if isinstance(activation, ReLUk):
            return activation.k >= 2
        return activation in (tanh, sigmoid, gelu, gelu_exact)

    def parameters(self, basis: ShallowNetBasis, dim: int, dtype) -> Array:
        """The network parameters `(α = 0, w, β)`, each `(S, D)`."""
        width = basis.width
        lo, hi = self.centres
        step = (hi - lo) / max(width - 1, 1)
        centres = np.array([lo + step * i for i in range(width)])
        signs = np.where(np.arange(width) % 2 == 0, 1.0, -1.0)
        if isinstance(basis.activation, ReLUk):
            # a rectified unit is zero on one side of its centre: the neurons centred outside
            # the step face it, or half of them would vanish there
            signs = np.where(centres <= 0, 1.0, np.where(centres >= 1, -1.0, signs))
        w = self.scale * signs
        columns = np.stack([w, -w * centres])  # (2, S)
        w_beta = np.repeat(columns[:, :, None], dim, axis=2)
        # assembled in NumPy: known when the step is traced, it compiles nothing
        return jnp.asarray(np.concatenate([np.zeros((width, dim)), w_beta[0], w_beta[1]]), dtype)


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
        with jax.ensure_compile_time_eval():
            return self._span(theta, ctx.basis, ctx.nodes, ctx.weights, ctx.q0.shape[0],
                              ctx.q0.dtype)

    def _span(self, theta: Array, basis: AbstractBasis, nodes: Array, weights: Array,
              dim: int, dtype) -> ProjectedSpan:
        # Known when the step is traced (see `feature_span`): NumPy where it rounds as JAX.
        known = not _traced(theta, basis, nodes, weights)
        xp = np if known else jnp
        host = np.asarray if known else _as_is
        nodes = xp.asarray(nodes).astype(dtype)
        n = nodes.shape[0]
        k = self.span_rank(basis, n)
        taus = xp.concatenate([nodes, xp.array([0.0, 1.0], dtype)])
        if isinstance(basis, ShallowNetBasis):
            _, w, beta = (host(a) for a in basis.split(host(theta)))
            hidden = (w, beta)
            z = w * taus[:, None, None] + beta  # (K, S, D)
            value, slope = (host(a) for a in jax.jvp(basis.activation, (z,), (xp.ones_like(z),)))
            slope = w * slope
        else:
            # A linear ansatz: its basis functions are the features, the same in every
            # coordinate (column j of the identity as parameters gives function j).
            hidden = ()
            eye = jnp.eye(basis.num_params(), dtype=dtype)
            value, slope = (host(a) for a in jax.vmap(
                lambda tau: jax.jvp(lambda t: basis.evaluate(eye, t), (tau,), (jnp.ones_like(tau),))
            )(taus))
            value = xp.repeat(value[:, :, None], dim, axis=2)  # (K, P, D)
            slope = xp.repeat(slope[:, :, None], dim, axis=2)
        rtol = self.rtol if self.rtol is not None else float(jnp.finfo(dtype).eps) ** 0.625
        span = feature_span(value, slope, weights, k, rtol, hidden)
        return span if known else jax.lax.stop_gradient(span)

    def reduce(self, curve: Callable[[Array], Array], span: ProjectedSpan, ctx: StepContext
               ) -> Array:
        """Coefficients `(k, D)` of a curve `τ ↦ q(τ)` (e.g. a network with any hidden layer)
        on `span`, by least squares in the quadrature's norm (the directions are orthogonal
        in it, so each coefficient is one inner product)."""
        dtype = ctx.q0.dtype
        b = ctx.weights.astype(dtype)
        q, dq = stage_values(curve, ctx.nodes.astype(dtype))
        ends = jax.vmap(curve)(jnp.array([0.0, 1.0], dtype))
        g1 = span.g1

        def inner(q, dq, e0, e1):
            return (jnp.einsum("j,djk,jd->kd", b, span.gq, q)
                    + jnp.einsum("j,djk,jd->kd", b, span.gv, dq)
                    + span.g0.T * e0 + g1.T * e1)

        norms = (jnp.einsum("j,djk->kd", b, span.gq**2) + jnp.einsum("j,djk->kd", b, span.gv**2)
                 + span.g0.T**2 + g1.T**2)
        c = inner(q, dq, ends[0], ends[1]) / jnp.where(span.live, norms, 1)
        return jnp.where(span.live, c, 0)

    def start(self, curve: Callable[[Array], Array], p1: Array, span: ProjectedSpan,
              ctx: StepContext) -> tuple[Array, Array]:
        """The unknowns `z = (δc, p_{n+1} − p_n)` of the curve `curve` and the end momentum
        `p1`: the Newton start."""
        dc = self.reduce(lambda tau: curve(tau) - ctx.q0, span, ctx)
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

    def reduced_residual_and_forces(self, z, args) -> tuple[tuple[Array, Array], Array]:
        """`reduced_residual` and the forces `∂L/∂q` at the nodes (`(R, D)`) it evaluated
        on the way: the step's dense output reads them at the converged `z`."""
        ctx, span = args[0], args[1]
        dc, dp = z
        q, dq = self.node_values(dc, span, ctx.q0)
        p, f = node_momenta_and_forces(ctx, q, dq)
        b = ctx.weights.astype(dc.dtype)
        # p_{n+1} g1 − p_n g0 with g1 = g0 + gd, p_{n+1} = p_n + Δp, term by term
        if dc.shape[1] == 1:
            forces = jnp.einsum("j,jd,djk->kd", ctx.h * b, f, span.gq)
            momenta = jnp.einsum("j,jd,djk->kd", b, p, span.gv)
        else:  # both as one batched product (fewer kernels; the same values)
            forces, momenta = jax.vmap(functools.partial(jnp.einsum, "j,jd,djk->kd"))(
                jnp.stack([ctx.h * b, b]), jnp.stack([f, p]), jnp.stack([span.gq, span.gv])
            )
        r = dp * span.g0.T + dp * span.gd.T + ctx.p0 * span.gd.T - forces - momenta
        r = jnp.where(span.live, r, dc)
        return (r, -jnp.einsum("dk,kd->d", span.g0, dc)), f

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
            # The four contractions as one batched one: a few kernels where four sets cost
            # twice as much (double pendulum: 1.3 us against 2.9 us), with the same values.
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
        `FixedPointIteration(matrix="kinetic")` applies: the iteration then contracts at a
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


class NewtonState(eqx.Module):
    """Where `RoundoffNewton`'s iteration stands (`FixedPointIteration`'s state extends it)."""

    f: Array
    step_norm: Array
    converged: Array
    at_floor: Array
    stalls: Array
    iterations: Array
    restarted: Array


class _LoopLayout(eqx.Module):
    """How a root finder's state rides through its loop: the fields its updates never
    change (`constant`) stay outside the loop, and its scalars are stacked as one vector in
    the widest of their floating dtypes, float32 at least, where counts and flags are
    exact."""

    treedef: Any = eqx.field(static=True)
    scalar: tuple[bool, ...] = eqx.field(static=True)
    dtypes: tuple[Any, ...] = eqx.field(static=True)
    work: Any = eqx.field(static=True)
    constant: dict

    @classmethod
    def of(cls, state, constant: tuple[str, ...]) -> _LoopLayout:
        leaves, treedef = jax.tree_util.tree_flatten(
            dataclasses.replace(state, **dict.fromkeys(constant))
        )
        scalar = tuple(jnp.ndim(leaf) == 0 for leaf in leaves)
        dtypes = tuple(jnp.result_type(leaf) for leaf in leaves)
        floats = [d for d, s in zip(dtypes, scalar, strict=True)
                  if s and jnp.issubdtype(d, jnp.floating)]
        work = jnp.result_type(jnp.float32, *floats)
        return cls(treedef, scalar, dtypes, work, {n: getattr(state, n) for n in constant})

    def pack(self, state) -> tuple[list, Array]:
        """The loop's carry of `state`: its other leaves, and its scalars as one vector."""
        leaves = jax.tree_util.tree_leaves(
            dataclasses.replace(state, **dict.fromkeys(self.constant))
        )
        rest = [leaf for leaf, s in zip(leaves, self.scalar, strict=True) if not s]
        packed = jnp.stack([jnp.asarray(leaf).astype(self.work)
                            for leaf, s in zip(leaves, self.scalar, strict=True) if s])
        return rest, packed

    def unpack(self, rest: list, packed: Array):
        """The state from `pack`'s output."""
        rest, leaves, k = iter(rest), [], 0
        for s, dtype in zip(self.scalar, self.dtypes, strict=True):
            if s:
                leaves.append(packed[k] != 0 if dtype == jnp.bool_ else packed[k].astype(dtype))
                k += 1
            else:
                leaves.append(next(rest))
        state = jax.tree_util.tree_unflatten(self.treedef, leaves)
        return dataclasses.replace(state, **self.constant)


class RoundoffNewton(AbstractStepRootFinder):
    """Newton's method for a square system with an isolated root, run to round-off.

    Each iteration solves `J d = −F` by LU with a fresh Jacobian (the hint `jacobian`, a
    function of the unknowns and `args`, where the caller gives one; else `jax.jacfwd`), or
    applies the hint `inverse` (the projected step's inverse by elimination without
    pivoting) where the caller gives one and it is finite. Far
    from the root a backtracking line search halves the step until `max|F|` falls; within
    `floor` of the root the full step is always taken. The solve ends as converged when
    `max|F| ≤ ftol · scale` (the hint `scale`) after an update within `√eps` of the
    unknowns (`confirm`), or when `max|F| ≤ floor · scale` and the Newton update has stopped
    shrinking (rounding has taken over). Quadratic convergence reaches either in a few
    iterations. Every
    solve makes at least one update, whatever the start's residual. It fails
    (`nonlinear_divergence`) after `max_stalls` line searches in a row find no decrease, and
    at the iteration cap.

    Given the hint `max_iterations` (the solver's iteration cap), the whole solve runs in
    one optimistix step, as compiled loops of updates that carry only what the iteration
    needs; `state.iterations` counts the updates. Given also the hint
    `restart = (first_try, start)`, a solve that has not converged after `first_try`
    iterations (or has stalled or become non-finite before) starts once more from
    `start(args)`, within the same cap; the test and the restart sit between two loops,
    not in every iteration, and `start` runs only where a solve needs it (under `vmap`:
    only if some member does). `state.restarted` says whether it did. Without the hint,
    each optimistix step is one update (`optimistix.root_find`'s `max_steps` is the cap).

    **Arguments:**

    - `ftol`: residual for immediate convergence, in units of `eps` of the working dtype
      times the residual scale. Default 64. `0` runs every solve to round-off: it ends only
      once the updates stop shrinking (the rule of `floor`), which removes the bias that
      the first accepted update's rounding leaves (see the benchmarks page on long runs).
    - `floor`: largest residual accepted once the updates stop shrinking, in the same units.
      Default 4096.
    - `confirm`: converge at `ftol` only after an update no larger than `√eps` times the
      unknowns (default `True`). The update that first brings the residual under `ftol`
      starts from the start's error, and the rounding of the iteration matrix leaves a part
      of that error behind which is a fixed linear function of the state: the same bias on
      every step, which makes the energy drift linearly (on the oscillator, thousandths of
      eps per step). One more update, from within `√eps`, shrinks that bias but does not
      remove it on every span; `ftol=0` does (the benchmarks page on long runs). It costs
      about one update per step; `False` skips it.
    - `max_backtracks`: halvings of the step in one line search. Default 20.
    - `max_stalls`: line searches in a row without decrease before giving up. Default 3.
    - `rtol`, `atol`, `norm`: unused; diffrax reads them off the root finder of an implicit
      solver.
    """

    hints_read: ClassVar[frozenset[str]] = frozenset(
        {"scale", "jacobian", "inverse", "max_iterations", "restart"}
    )

    ftol: float = 64.0
    floor: float = 4096.0
    confirm: bool = eqx.field(static=True, default=True)
    max_backtracks: int = eqx.field(static=True, default=20)
    max_stalls: int = eqx.field(static=True, default=3)
    rtol: float | None = None
    atol: float | None = None
    norm: Callable = optx.max_norm

    def __check_init__(self):
        for name, least in (("ftol", 0), ("floor", 1e-300)):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and not isinstance(value, bool)
                    and value >= least and math.isfinite(value)):
                kind = "a non-negative" if least == 0 else "a positive"
                raise ValueError(f"{name} must be {kind} number (of eps), got {value!r}")
        if not isinstance(self.confirm, bool):
            raise TypeError(f"confirm must be True or False, got {self.confirm!r}")
        if self.floor < self.ftol:
            raise ValueError(f"floor ({self.floor}) must be at least ftol ({self.ftol})")
        for name in ("max_backtracks", "max_stalls"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")

    def _tolerance(self, name: str, dtype) -> float:
        return getattr(self, name) * float(jnp.finfo(dtype).eps)

    @staticmethod
    def _confirmed(norm: Array, y: Array, dtype) -> Array:
        """Whether the last update (`max|Δz| = norm`) is within `√eps` of the unknowns `y`
        (`confirm`)."""
        return norm <= float(jnp.finfo(dtype).eps) ** 0.5 * jnp.max(jnp.abs(y))

    @staticmethod
    def _jacobian(fn, y, args, options) -> Array:
        """The Jacobian at `y`: the hint `jacobian` where the caller gives one, else
        `jax.jacfwd` of the flattened residual."""
        given = hints_of(options).jacobian
        if given is not None:
            return given(y, args)
        flat, unravel = ravel_pytree(y)
        return jax.jacfwd(lambda v: ravel_pytree(fn(unravel(v), args)[0])[0])(flat)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del aux_struct, tags, f_struct
        del options
        f, _ = fn(y, args)
        flat = ravel_pytree(f)[0]
        inf = jnp.full((), jnp.inf, flat.dtype)
        # Never converged at the start: in low precision the tolerance can be as large as the
        # start's residual, and a step must make at least one Newton update.
        no = jnp.array(False)
        return NewtonState(flat, inf, no, no, jnp.array(0, jnp.int32), jnp.array(0, jnp.int32),
                            no)

    def step(self, fn, y, args, options, state, tags):
        del tags
        hints = hints_of(options)
        if hints.max_iterations is None:
            if hints.restart is not None:
                raise ValueError("the hint `restart` needs the hint `max_iterations`")
            return self._update(fn, y, args, options, state)
        return self._whole_solve(fn, y, args, options, state, hints)

    def _whole_solve(self, fn, y, args, options, state, hints: StepHints):
        """The solve from `y` to its end, in compiled loops of `_update`: up to `first_try`
        iterations, the restart where that try ended unconverged, then the rest up to
        `max_iterations`. The restart's test and branch run once per solve, not on every
        iteration; where both tries take the same update, it is compiled once (a loop over
        the tries)."""
        cap = hints.max_iterations
        # the carry's aux before the first update: zeros of its shape (nothing evaluated)
        aux = jax.tree_util.tree_map(
            lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(lambda: fn(y, args)[1])
        )
        carry = (y, state, aux)
        if hints.restart is None or hints.restart[0] >= cap:
            return self._whole_solve_loop(fn, args, options, carry, cap)
        first_try, start = hints.restart

        def restarted(carry, need):
            return unless_all_skip(
                need, lambda: self._restarted(fn, start(args), args, options, carry), carry
            )

        def unconverged(carry):
            state = carry[1]
            return ~(state.converged | state.at_floor) & (state.iterations < cap)

        second = self._second_try()
        if second is not self:
            carry = self._whole_solve_loop(fn, args, options, carry, first_try)
            carry = restarted(carry, unconverged(carry))
            return second._whole_solve_loop(fn, args, options, carry, cap)

        def cond(outer):
            tries, carry = outer
            return (tries == 0) | ((tries == 1) & unconverged(carry))

        def body(outer):
            tries, carry = outer
            carry = restarted(carry, (tries > 0) & unconverged(carry))
            limit = jnp.where(tries > 0, cap, first_try)
            return tries + 1, self._whole_solve_loop(fn, args, options, carry, limit)

        return jax.lax.while_loop(cond, body, (jnp.array(0, jnp.int32), carry))[1]

    def _loop_constants(self) -> tuple[str, ...]:
        """The fields of the state that `_update` never changes (kept out of the loop)."""
        return ("restarted",)

    def _second_try(self) -> RoundoffNewton:
        """The root finder whose updates follow a restart (this one)."""
        return self

    def _whole_solve_loop(self, fn, args, options, carry, limit):
        """`_update` from `carry = (y, state, aux)` until the solve ends or has made `limit`
        updates in all.

        The loop carries the state's scalars (norms, flags, counts) as one small vector, and
        not the fields the updates leave alone (`_loop_constants`): an update then ends in a
        few kernels instead of one for each scalar and its copy, which at the sizes of a
        step cost as much as the residual."""
        y, state, aux = carry
        layout = _LoopLayout.of(state, self._loop_constants())

        def cond(carry):
            state = layout.unpack(carry[1], carry[2])
            done, _ = self._ended(state)
            return ~done & (state.iterations < limit)

        def body(carry):
            y, state, aux = self._update(fn, carry[0], args, options,
                                         layout.unpack(carry[1], carry[2]))
            return (y, *layout.pack(state), aux)

        y, rest, packed, aux = jax.lax.while_loop(cond, body, (y, *layout.pack(state), aux))
        return y, layout.unpack(rest, packed), aux

    def _restarted(self, fn, start, args, options, carry):
        """`carry = (y, state, aux)` moved to the point `start`, with fresh bookkeeping."""
        y, state, aux = carry
        dtype = ravel_pytree(y)[0].dtype
        _, unravel = ravel_pytree(y)
        point = unravel(ravel_pytree(start)[0].astype(dtype))
        f, _ = fn(point, args)
        inf = jnp.full((), jnp.inf, dtype)
        no = jnp.array(False)
        zero = jnp.zeros_like(state.stalls)
        fresh = NewtonState(ravel_pytree(f)[0], inf, no, no, zero, state.iterations,
                            jnp.array(True))
        return point, fresh, aux

    def _update(self, fn, y, args, options, state):
        """One Newton update from `y` (with backtracking far from the root)."""
        flat_y, unravel = ravel_pytree(y)
        dtype = flat_y.dtype
        scale = jnp.asarray(hints_of(options).scale, dtype)

        def residual(v):
            out, aux = fn(unravel(v), args)
            return ravel_pytree(out)[0], aux

        d = self._direction(fn, y, args, options, state.f)
        fmax = jnp.max(jnp.abs(state.f))
        near = fmax <= self._tolerance("floor", dtype) * scale
        f_full, aux_full = residual(flat_y + d)

        def enough(f_try, a):
            return near | (jnp.max(jnp.abs(f_try)) <= (1 - 1e-4 * a) * fmax)

        def cond(carry):
            a, f_try, _, k = carry
            return ~enough(f_try, a) & (k < self.max_backtracks)

        def body(carry):
            a, _, _, k = carry
            a = a / 2
            f_try, aux = residual(flat_y + a * d)
            return a, f_try, aux, k + 1

        one = jnp.ones((), dtype)
        a, f_new, aux, _ = jax.lax.while_loop(cond, body, (one, f_full, aux_full, 0))
        decreased = enough(f_new, a)
        new = jnp.where(decreased, flat_y + a * d, flat_y)
        f_new = jnp.where(decreased, f_new, state.f)
        fmax_new = jnp.max(jnp.abs(f_new))
        norm = jnp.max(jnp.abs(a * d))
        iterations = state.iterations + 1
        converged = fmax_new <= self._tolerance("ftol", dtype) * scale
        if self.confirm:
            converged = converged & self._confirmed(norm, new, dtype)
        # Rounding has taken over once a full update near the root is no smaller than the
        # one before it.
        at_floor = near & (norm >= state.step_norm) & (
            fmax_new <= self._tolerance("floor", dtype) * scale
        )
        stalls = jnp.where(decreased, 0, state.stalls + 1)
        step_norm = jnp.where(decreased, norm, state.step_norm)
        state = NewtonState(f_new, step_norm, converged, at_floor, stalls, iterations,
                            state.restarted)
        return unravel(new), state, aux

    def _direction(self, fn, y, args, options, f: Array) -> Array:
        """Newton's update `−J⁻¹ F` at `y`: with the hint `inverse` where the caller gives
        one (the formulation's own inverse, cheaper than LAPACK at the sizes of a step; by
        LU where it is not finite), else by LU of the Jacobian."""
        dtype = f.dtype
        jac = self._jacobian(fn, y, args, options)

        def by_lu():
            return solve(jac.astype(dtype), -f)

        given = hints_of(options).inverse
        if given is None:
            return by_lu()
        inverse = given(jac, y, args)
        d = -(inverse @ f.astype(inverse.dtype)).astype(dtype)
        # a non-finite inverse makes the update non-finite: testing the update is cheaper
        return unless_all_skip(~jnp.all(jnp.isfinite(d)), by_lu, d)

    def _ended(self, state: NewtonState):
        """Whether the solve has ended at `state`, and how."""
        fmax = jnp.max(jnp.abs(state.f))
        nonfinite = ~jnp.isfinite(fmax)
        stalled = state.stalls >= self.max_stalls
        result = optx.RESULTS.where(
            nonfinite,
            optx.RESULTS.nonfinite,
            optx.RESULTS.where(stalled, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful),
        )
        return state.converged | state.at_floor | nonfinite | stalled, result

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, tags
        done, result = self._ended(state)
        if hints_of(options).max_iterations is None:
            return done, result
        # The whole solve ran in the first step (`_whole_solve`); a start that has already
        # ended (a non-finite residual) is not stepped at all.
        ran = (state.iterations > 0) | done
        result = optx.RESULTS.where(
            done, result, optx.RESULTS.nonlinear_max_steps_reached
        )
        return ran, optx.RESULTS.where(ran, result, optx.RESULTS.successful)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}
