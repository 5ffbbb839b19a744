"""Dense linear algebra in the working precision.

LAPACK has no half precision, so below 32 bits the factorisations run in float32
(`precision.lapack_dtype`) and only the results are rounded back to the working dtype: a float16
run stays float16 at every interface.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._precision import lapack_dtype

__all__ = ["solve", "constant_outer", "constant_product", "damped_least_squares",
           "dense_tangent_solve", "elimination_solve", "regular_inverse", "unpivoted_inverse",
           "well_conditioned"]


def solve(matrix: Array, rhs: Array) -> Array:
    """`matrix⁻¹ rhs` in the dtype of `rhs`."""
    dtype = jnp.result_type(rhs)
    work = lapack_dtype(dtype)
    return jnp.linalg.solve(matrix.astype(work), rhs.astype(work)).astype(dtype)


def elimination_solve(matrix: Array, rhs: Array) -> Array:
    """`matrix⁻¹ rhs` (`rhs` a vector) by Gaussian elimination with partial pivoting, written
    in elementwise operations and reductions only, in the dtype of `rhs`.

    No LAPACK call and no matrix product: XLA's CPU backend compiles a loop free of such
    calls (library calls, the dot library's fusions) whole when it is small enough
    (`xla_cpu_small_while_loop_byte_threshold`), without a runtime dispatch per operation;
    one of them anywhere in a step keeps every loop around it out of that. For the small,
    rarely formed systems of a step (a fallback's Newton iteration). A singular matrix gives
    non-finite entries, which the caller must check. Below 32 bits it works in float32, as
    the factorisations do.
    """
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or rhs.shape != matrix.shape[:1]:
        raise ValueError("elimination_solve needs a square matrix and a vector of its size, "
                         f"got shapes {matrix.shape} and {rhs.shape}")
    dtype = jnp.result_type(rhs)
    work = lapack_dtype(dtype)
    n = matrix.shape[0]
    index = jnp.arange(n)

    def eliminate(k, ab):
        # the row of largest |entry| in column k, at or below row k, swapped with row k (by
        # masks: no gather or scatter), then column k cleared below the diagonal
        column = jax.lax.dynamic_index_in_dim(ab, k, 1, keepdims=False)
        pivot_at = jnp.argmax(jnp.where(index >= k, jnp.abs(column), -1))
        row_k = jax.lax.dynamic_index_in_dim(ab, k, 0, keepdims=False)
        row_p = jnp.sum(jnp.where((index == pivot_at)[:, None], ab, 0), axis=0)
        ab = jnp.where((index == k)[:, None], row_p,
                       jnp.where((index == pivot_at)[:, None], row_k, ab))
        column = jax.lax.dynamic_index_in_dim(ab, k, 1, keepdims=False)
        factors = jnp.where(index > k, column / row_p[k], 0)
        return ab - factors[:, None] * row_p[None, :]

    ab = jnp.concatenate([matrix.astype(work), rhs.astype(work)[:, None]], axis=1)
    ab = jax.lax.fori_loop(0, n, eliminate, ab)
    upper, b = ab[:, :n], ab[:, n]

    def substitute(i, x):
        k = n - 1 - i
        row = jax.lax.dynamic_index_in_dim(upper, k, 0, keepdims=False)
        value = (b[k] - jnp.sum(jnp.where(index > k, row * x, 0))) / row[k]
        return jnp.where(index == k, value, x)

    return jax.lax.fori_loop(0, n, substitute, jnp.zeros_like(b)).astype(dtype)


def dense_tangent_solve(linear, rhs):
    """`x` with `linear(x) = rhs` (pytrees of one structure), by a dense factorisation of the
    linear map: the `tangent_solve` of `jax.lax.custom_root` for a step's equations at their
    root (formed only where a derivative is taken)."""
    from jax.flatten_util import ravel_pytree

    flat, unravel = ravel_pytree(rhs)
    matrix = jax.jacfwd(lambda v: ravel_pytree(linear(unravel(v)))[0])(jnp.zeros_like(flat))
    return unravel(jnp.linalg.solve(matrix, flat))


def damped_least_squares(matrix: Array, rhs: Array, sqrt_mu: Array) -> Array:
    """`argmin_d ‖matrix·d − rhs‖² + μ‖d‖²`, by QR of `[matrix; √μ I]` (no normal equations).

    The right-hand side rides along as an extra column of the factorised matrix, so the
    factorisation's triangle already holds `Qᵀ·rhs` and `Q` is never formed: about half the
    work of a QR that returns `Q`, with the same result up to rounding.
    """
    dtype = jnp.result_type(rhs)
    work = lapack_dtype(dtype)
    n = matrix.shape[1]
    column = rhs.ndim == 1
    rhs = rhs.astype(work)[:, None] if column else rhs.astype(work)
    k = rhs.shape[1]
    top = jnp.concatenate([matrix.astype(work), rhs], axis=1)
    bottom = jnp.concatenate(
        [jnp.asarray(sqrt_mu, work) * jnp.eye(n, dtype=work), jnp.zeros((n, k), work)], axis=1
    )
    r = jnp.linalg.qr(jnp.concatenate([top, bottom], axis=0), mode="r")
    d = jax.scipy.linalg.solve_triangular(r[:n, :n], r[:n, n:])
    return (d[:, 0] if column else d).astype(dtype)


def unpivoted_inverse(matrix: Array, order: np.ndarray | None = None) -> Array:
    """`matrix⁻¹` by Gauss–Jordan elimination without pivoting, taking the rows in `order`
    (a fixed permutation, known when traced, that puts large entries on the diagonal;
    default: as they are).

    One compiled loop over the columns, each elimination one fused rank-one update: at the
    sizes of a step (tens of unknowns) on a CPU it launches far fewer kernels than LAPACK's
    LU and triangular solves, and under `vmap` it is plain batched arithmetic. Without
    pivoting it suits only matrices whose leading minors, in `order`, stay away from zero; a
    zero pivot makes the result non-finite, which the caller must check. Below 32 bits it
    works in float32, as the factorisations do. Under `vmap` the members sit on the last
    axis, so that each update runs over all members at once in contiguous memory.
    """
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise ValueError(f"unpivoted_inverse needs a square matrix, got shape {matrix.shape}")
    n = matrix.shape[-1]
    if order is not None:
        order = np.asarray(order)
        if order.shape != (n,) or not np.array_equal(np.sort(order), np.arange(n)):
            raise ValueError(f"order must be a permutation of range({n}), got {order!r}")
    a = matrix.astype(lapack_dtype(matrix.dtype))
    if order is not None:
        a = a[order]
    a = _inverse(a)
    if order is not None:
        # (P A)⁻¹ = A⁻¹ P⁻¹: the inverse of `matrix` has the columns of `a` in row order
        a = a[:, np.argsort(order)]
    return a


@jax.custom_jvp
def _inverse(a: Array) -> Array:
    """`a⁻¹` by `_gauss_jordan`, differentiated as an inverse (`d(A⁻¹) = −A⁻¹ dA A⁻¹`): the
    batching rule below has no derivative of its own."""
    return _gauss_jordan(a)


@_inverse.defjvp
def _inverse_jvp(primals, tangents):
    (a,), (da,) = primals, tangents
    inverse = _inverse(a)
    return inverse, -inverse @ da @ inverse


@jax.custom_batching.custom_vmap
def _gauss_jordan(a: Array) -> Array:
    """The inverse of `a` by Gauss–Jordan elimination in place, without pivoting."""
    n = a.shape[-1]
    index = jnp.arange(n)

    def eliminate(k, a):
        # column k's elimination in place: row k scaled by its pivot, the others cleared in
        # column k; column k ends as the inverse's column (the pivot's slot holds 1/p). The
        # outer product as a (n, 1) x (1, n) matrix product: fewer kernels on a CPU than
        # the broadcast one.
        row = jax.lax.dynamic_slice_in_dim(a, k, 1, 0)  # (1, n)
        column = jax.lax.dynamic_slice_in_dim(a, k, 1, 1)  # (n, 1)
        pivot = jax.lax.dynamic_slice_in_dim(row, k, 1, 1)  # (1, 1)
        here = (index >= k) & (index < k + 1)  # (as a range: faster code than `==` here)
        pivot_row = (1 / pivot) @ jnp.where(here[None, :], 1, row)
        multipliers = jnp.where(here[:, None], -1, column)
        outside = ~here[:, None] & ~here[None, :]
        return jnp.where(outside, a, 0) - multipliers @ pivot_row

    return jax.lax.fori_loop(0, n, eliminate, a)


@_gauss_jordan.def_vmap
def _gauss_jordan_members(axis_size, in_batched, a):
    """`_gauss_jordan` of many members: the same elimination with the members on the last
    axis, where every step is one update over all of them (a vmap of the loop above would
    keep them first, and each member's small matrix apart)."""
    del axis_size
    if not in_batched[0]:
        return _gauss_jordan(a), False
    a = jnp.moveaxis(a, 0, -1)  # (n, n, members)
    n = a.shape[0]
    index = jnp.arange(n)

    def eliminate(k, a):
        row = jax.lax.dynamic_index_in_dim(a, k, 0, keepdims=False)  # (n, members)
        column = jax.lax.dynamic_index_in_dim(a, k, 1, keepdims=False)  # (n, members)
        pivot = jax.lax.dynamic_index_in_dim(row, k, 0, keepdims=False)  # (members,)
        here = (index == k)[:, None]
        pivot_row = (1 / pivot) * jnp.where(here, 1, row)  # (as in the loop above)
        multipliers = jnp.where(here, -1, column)
        outside = ~here[:, None] & ~here[None, :]
        return jnp.where(outside, a, 0) - multipliers[:, None, :] * pivot_row[None, :, :]

    return jnp.moveaxis(jax.lax.fori_loop(0, n, eliminate, a), -1, 0), True


def well_conditioned(matrix) -> bool:
    """Whether a matrix known when the step is traced is invertible well within float64
    (condition number below 1e12): e.g. a regular Lagrangian's constant kinetic matrix."""
    return bool(np.linalg.cond(np.asarray(matrix)) < 1e12)


def regular_inverse(matrix: np.ndarray, dtype) -> np.ndarray | bool | None:
    """The inverse of a matrix known when the step is traced (NumPy), `True` for the
    identity, or `None` where it is singular in `dtype` (condition number past 1/eps)."""
    matrix = np.asarray(matrix, np.float64)
    if not np.all(np.isfinite(matrix)) or np.linalg.cond(matrix) >= 1 / np.finfo(dtype).eps:
        return None
    if np.array_equal(matrix, np.eye(matrix.shape[0])):
        return True
    return np.linalg.inv(matrix)


def constant_product(matrix: np.ndarray, values: Array, fused: bool = True) -> Array:
    """`matrix @ values` for a constant `matrix` (`(m, n)` against `(n, D)`), laid out for
    how it runs: alone, as one fused multiply and a reduction over the minor axis (a `dot`
    of these sizes costs more in its call than in its arithmetic); under `vmap`, as one
    batched `dot` (where the fused form's reduction runs over a strided axis). `fused=False`
    keeps the multiply-reduce form under `vmap` too, for what is differentiated (the batching
    rule has no derivative rule) and for loops that must hold no call of the dot library
    (`newton_solve`)."""
    constant = np.asarray(matrix, np.float64)

    def product(values):
        m = jnp.asarray(constant, values.dtype)
        return jnp.sum(m[None, :, :] * values.T[:, None, :], axis=-1).T

    if not fused:
        return product(values)
    apply = jax.custom_batching.custom_vmap(product)

    @apply.def_vmap
    def _batched(axis_size, in_batched, values):
        del axis_size
        if not in_batched[0]:
            return product(values), False
        m = jnp.asarray(constant, values.dtype)
        return jnp.einsum("ij,bjd->bid", m, values), True

    return apply(values)


def constant_outer(vector: np.ndarray, row: Array) -> Array:
    """`vector ⊗ row` for a constant `vector`."""
    return jnp.stack([float(c) * row for c in np.asarray(vector)])
