"""The feature span of a projected step, orthonormalised in the quadrature's norm.

A projected step (`VariableProjection`) moves its curve only within the span of a fixed set
of feature functions (a network's hidden layer, or a linear ansatz's basis functions). Nearly
collinear features make that span numerically smaller than their number, so it is first
orthonormalised in the norm the quadrature sees (a thin SVD of the weighted data of the
features, per coordinate) and only its leading directions are kept. One of them is the
constant function, exactly, so that the step's unknowns are increments that keep the digits
the state's size would round away.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._precision import lapack_dtype

__all__ = ["ProjectedSpan", "any_traced", "feature_span"]


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
    NumPy, SVDs included: evaluated by JAX operation by operation, each operation would
    compile a program of its own (seconds of a first call). NumPy's LAPACK rounds otherwise
    than XLA's, so the directions agree with those of a traced span to rounding, each up to
    its sign: the same span."""
    known = not any_traced(value, slope, weights, hidden)
    xp = np if known else jnp
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
    svd = functools.partial(xp.linalg.svd, full_matrices=False)
    # The constant's output weights: least squares on the features.
    u_a, s_a, vt_a = svd(data)
    top = s_a[..., :1]
    keep = s_a > rtol * top
    inv_a = xp.where(keep, 1 / xp.where(keep, s_a, 1), 0)
    alpha_one = xp.einsum("dks,dk->ds", vt_a, inv_a * xp.einsum("dik,i->dk", u_a, one))
    # The features with the constant projected out, orthonormalised.
    per_norm2 = 1 / xp.dot(one, one)
    along = xp.einsum("i,dis->ds", one, data) * per_norm2  # (D, S)
    rest = data - one[None, :, None] * along[:, None, :]
    u, s, vt = svd(rest)
    m = rank - 1
    u, s, v = u[..., :m], s[..., :m], xp.swapaxes(vt, 1, 2)[..., :m]
    live = s > rtol * top
    inv = xp.where(live, 1 / xp.where(live, s, 1), 0)
    # Direction k is `features·w_k − (along·w_k)·1`; the weak ones are orthogonal to the
    # constant only to eps/s_k, so it is projected out once more (`γ_k` of the constant).
    gamma = xp.einsum("i,dik->dk", one, u) * per_norm2
    u = u - one[None, :, None] * gamma[:, None, :]
    weights_rest = v * inv[:, None, :]  # (D, S, m)
    shift = xp.einsum("ds,dsk->dk", along, weights_rest) + gamma
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


def any_traced(*trees) -> bool:
    """Whether any leaf of `trees` is traced (else all are known when the step is traced)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(trees))
