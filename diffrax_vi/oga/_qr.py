"""Small dense factorisations for the greedy fit, written in plain `jax.numpy`.

Two pieces, both with static shapes so they run inside `lax` loops and under `vmap`, and both
computed entirely in the dtype of their inputs (so they also work in float16, where LAPACK
routines are not available):

- an *incremental* QR factorisation of the selected design, grown one column at a time by
  classical Gram–Schmidt with one re-orthogonalisation pass (CGS2); its `R` diagonal entry is
  the rank gain of the new column;
- a column-pivoted Householder least-squares solve with a relative rank cut, used by the
  refits; dependent or unused (all-zero) columns get a zero coefficient;
- a one-sided Jacobi SVD, an upper-triangular back substitution and an LU solve with partial
  pivoting, for the other refits.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._precision import as_dtype, eps, norm2, sumsq

__all__ = [
    "QRState",
    "qr_init",
    "qr_append",
    "pivoted_lstsq",
    "jacobi_svd",
    "upper_solve",
    "lu_solve",
]


class QRState(NamedTuple):
    """Thin QR factors `A[:, :k] = Q[:, :k] R[:k, :k]` of the first `k` design columns.

    Columns of `Q` (and rows/columns of `R`) at positions `>= k` are kept at zero, so
    products with the full arrays need no mask.

    **Arguments:**

    - `q`: `(M, K)` orthonormal columns (zero past `k`).
    - `r`: `(K, K)` upper triangle (zero past `k`).
    - `k`: number of columns factorised so far (int32 scalar).
    """

    q: Array
    r: Array
    k: Array


def qr_init(num_rows: int, num_cols: int, dtype) -> QRState:
    """An empty factorisation with room for `num_cols` columns of length `num_rows`."""
    return QRState(
        q=jnp.zeros((num_rows, num_cols), dtype),
        r=jnp.zeros((num_cols, num_cols), dtype),
        k=jnp.zeros((), jnp.int32),
    )


def qr_append(state: QRState, column: Array, min_gain: Array) -> tuple[QRState, Array, Array]:
    """Try to append one column to the factorisation.

    The column is orthogonalised against the current `Q` twice (CGS2). Its remaining norm
    `rho` is the rank gain. The column is refused (the state is returned unchanged) when `rho`
    is not finite or `rho <= min_gain * ||column||`; with `min_gain = 0` only a column that
    adds no direction at all (or overflows) is refused.

    **Arguments:**

    - `state`: the current factorisation; must have room for one more column.
    - `column`: the candidate column, same dtype as the state.
    - `min_gain`: relative gain floor (a scalar of the working dtype).

    **Returns:**

    `(new_state, rho, accepted)`.
    """
    q, r, k = state
    u = column
    coeffs = jnp.zeros(r.shape[0], column.dtype)
    for _ in range(2):
        c = q.T @ u
        u = u - q @ c
        coeffs = coeffs + c
    rho = norm2(u)
    accepted = jnp.isfinite(rho) & (rho > min_gain * norm2(column))
    safe_rho = jnp.where(accepted, rho, as_dtype(1, rho.dtype))
    # One-hot selects instead of scatters: the arrays are tiny and this compiles faster.
    slot = jnp.arange(r.shape[0]) == k
    q_new = jnp.where(slot[None, :], (u / safe_rho)[:, None], q)
    r_new = jnp.where(slot[None, :], jnp.where(slot, rho, coeffs)[:, None], r)
    new = QRState(
        q=jnp.where(accepted, q_new, q),
        r=jnp.where(accepted, r_new, r),
        k=jnp.where(accepted, k + 1, k),
    )
    return new, rho, accepted


def pivoted_lstsq(a: Array, b: Array, rtol: Array) -> Array:
    """Least-squares solution of `a x ≈ b` by Householder QR with column pivoting.

    At step `i` the column with the largest remaining norm is moved to position `i` (first
    index on ties) and reduced by a Householder reflector. The factorisation stops at the
    numerical rank: the first step whose pivot `|alpha|` is non-finite or at most
    `rtol * |alpha_0|`. The leading triangle is then solved and every column beyond the rank
    (dependent ones, and all-zero columns such as unused slots of a masked design) gets a
    zero coefficient: the "basic" solution, not the minimum-norm one. Column norms are
    recomputed from the reduced matrix at every step rather than downdated.

    **Arguments:**

    - `a`: the `(M, K)` design.
    - `b`: the `(M,)` right-hand side, same dtype.
    - `rtol`: relative rank cut on the pivots (a scalar of the working dtype).

    **Returns:**

    The `(K,)` coefficients in the original column order (finite unless the data overflow).
    """
    m, n = a.shape
    dtype = a.dtype
    zero = as_dtype(0, dtype)
    one = as_dtype(1, dtype)
    rows = jnp.arange(m)
    cols = jnp.arange(n + 1)  # the right-hand side rides along as column n

    def step(i, carry):
        ab, perm, rank, active, pivot0 = carry
        below = rows >= i
        cnorm = jnp.where(
            (cols >= i) & (cols < n), sumsq(jnp.where(below[:, None], ab, zero), axis=0), -one
        )
        p = jnp.argmax(cnorm)
        # Swap columns i and p (of the matrix and of the permutation).
        at_i, at_p = cols == i, cols == p
        col_i, col_p = ab[:, i], ab[:, p]
        ab = jnp.where(at_p[None, :], col_i[:, None], jnp.where(at_i[None, :], col_p[:, None], ab))
        perm = jnp.where(at_i[:n], perm[p], jnp.where(at_p[:n], perm[i], perm))
        # Householder reflector H = I - beta v v^T mapping rows i.. of the pivot column to
        # alpha e_i; the reduction stops (beta = 0, H = I) once the pivot is below the cut.
        x = jnp.where(below, col_p, zero)
        nx = norm2(x)
        alpha = jnp.where(x[i] >= 0, -nx, nx)
        v = jnp.where(rows == i, x - alpha, x)
        vtv = sumsq(v)
        pivot0 = jnp.where(i == 0, jnp.abs(alpha), pivot0)
        active = active & jnp.isfinite(alpha) & (jnp.abs(alpha) > rtol * pivot0)
        usable = active & (nx > 0) & (vtv > 0)
        beta = jnp.where(usable, 2 / jnp.where(usable, vtv, one), zero)
        # Columns before i are zero in rows >= i and stay as they are; column i becomes
        # (R[:i, i], alpha, 0, ...); the trailing columns and the rhs are reflected.
        reflected = ab - jnp.outer(beta * v, v @ ab)
        new_col = jnp.where(below, jnp.where(rows == i, alpha, zero), col_p)
        new_col = jnp.where(active, new_col, col_p)
        ab = jnp.where(
            at_i[None, :], new_col[:, None], jnp.where((cols > i)[None, :], reflected, ab)
        )
        rank = jnp.where(active, i + 1, rank)
        return ab, perm, rank, active, pivot0

    init = (
        jnp.concatenate([a, b[:, None]], axis=1),
        jnp.arange(n, dtype=jnp.int32),
        jnp.zeros((), jnp.int32),
        jnp.ones((), bool),
        zero,
    )
    ab, perm, rank, _, _ = lax.fori_loop(0, min(m, n), step, init)

    # Back substitution on the leading rank x rank triangle; entries past the rank are zero.
    if m < n:  # a wide design: pad to square so that row i exists for every column i
        ab = jnp.concatenate([ab, jnp.zeros((n - m, n + 1), dtype)], axis=0)
    ncols = jnp.arange(n)

    def back(j, z):
        i = n - 1 - j
        row = ab[i]
        live = i < rank
        diag = jnp.where(live, row[i], one)
        val = (row[n] - jnp.where(ncols > i, row[:n], zero) @ z) / diag
        return jnp.where(ncols == i, jnp.where(live, val, zero), z)

    z = lax.fori_loop(0, n, back, jnp.zeros((n,), dtype))
    # Undo the permutation: coefficient of original column perm[i] is z[i].
    return jnp.sum(jnp.where(perm[:, None] == ncols[None, :], z[:, None], zero), axis=0)


def upper_solve(r: Array, rhs: Array, live: Array) -> Array:
    """Back substitution `R z = rhs` on the live part of an upper triangle.

    Entries of `z` where `live` is false are zero and their rows are skipped (their diagonal is
    treated as one). A zero diagonal in a live row gives a non-finite result, which the
    guarded refit replaces.

    **Arguments:**

    - `r`: `(K, K)` upper triangle.
    - `rhs`: `(K,)` right-hand side.
    - `live`: `(K,)` booleans, the rows and columns that take part.
    """
    n = r.shape[0]
    dtype = r.dtype
    zero = as_dtype(0, dtype)
    one = as_dtype(1, dtype)
    idx = jnp.arange(n)

    def back(j, z):
        i = n - 1 - j
        row = r[i]
        diag = jnp.where(live[i], row[i], one)
        val = (rhs[i] - jnp.where(idx > i, row, zero) @ z) / diag
        return jnp.where(idx == i, jnp.where(live[i], val, zero), z)

    return lax.fori_loop(0, n, back, jnp.zeros((n,), dtype))


def lu_solve(g: Array, rhs: Array) -> Array:
    """Solve the square system `G x = rhs` by Gaussian elimination with partial pivoting.

    At step `i` the row with the largest `|G[j, i]|`, `j >= i`, becomes the pivot row (first
    index on ties). An exactly zero pivot is not caught: the result is then non-finite, and
    the guarded refit falls back to the ridged solve (the analogue of a singular-matrix
    exception). Computed in the dtype of `g`.
    """
    n = g.shape[0]
    dtype = g.dtype
    zero = as_dtype(0, dtype)
    rows = jnp.arange(n)
    cols = jnp.arange(n + 1)

    def step(i, ab):
        col = jnp.where(rows >= i, jnp.abs(ab[:, i]), -as_dtype(1, dtype))
        p = jnp.argmax(col)
        row_i, row_p = ab[i], ab[p]
        ab = jnp.where((rows == p)[:, None], row_i[None, :], ab)
        ab = jnp.where((rows == i)[:, None], row_p[None, :], ab)
        pivot = row_p[i]
        factors = jnp.where(rows > i, ab[:, i] / pivot, zero)
        ab = ab - factors[:, None] * jnp.where(cols >= i, row_p, zero)[None, :]
        return ab

    ab = lax.fori_loop(0, n, step, jnp.concatenate([g, rhs[:, None]], axis=1))
    return upper_solve(ab[:, :n], ab[:, n], jnp.ones((n,), bool))


def jacobi_svd(a: Array, max_sweeps: int = 30) -> tuple[Array, Array, Array]:
    """Thin SVD `a = U diag(s) V^T` by one-sided (Hestenes) Jacobi rotations.

    Sweeps visit the column pairs `(i, j)`, `i < j`, in lexicographic order and rotate the
    pair until it is orthogonal. A pair is skipped when `beta = <a_i, a_j>` is zero or not
    finite, or `|beta| <= eps sqrt(alpha) sqrt(gamma)` with `alpha`, `gamma` the squared column
    norms: the two square roots are taken separately, because `sqrt(alpha gamma)` overflows
    in float16 once column norms pass about 16, which would silently skip every rotation.
    Stops after a sweep without rotation, or after `max_sweeps` sweeps. Everything is in the
    dtype of `a` (so it also runs in float16).

    **Arguments:**

    - `a`: the `(M, K)` matrix.
    - `max_sweeps`: the sweep budget (static; default 30).

    **Returns:**

    `(u, s, v)`: `u` `(M, K)` with unit columns (zero where `s` is zero or not finite), `s`
    `(K,)` the column norms after rotation, **unsorted** (in the column order of `v`), and `v`
    `(K, K)` orthogonal.
    """
    m, n = a.shape
    dtype = a.dtype
    e = eps(dtype)
    zero = as_dtype(0, dtype)
    one = as_dtype(1, dtype)
    two = as_dtype(2, dtype)
    pi_, pj_ = np.triu_indices(n, 1)
    pairs_i = jnp.asarray(pi_, jnp.int32)
    pairs_j = jnp.asarray(pj_, jnp.int32)
    npairs = int(pi_.shape[0])
    colid = jnp.arange(n)

    def rotate(p, carry):
        b, v, rotated = carry
        i, j = pairs_i[p], pairs_j[p]
        bi, bj = b[:, i], b[:, j]
        alpha, gamma, beta = sumsq(bi), sumsq(bj), bi @ bj
        skip = (
            (beta == 0)
            | ~jnp.isfinite(beta)
            | (jnp.abs(beta) <= e * jnp.sqrt(alpha) * jnp.sqrt(gamma))
        )
        safe_beta = jnp.where(skip, one, beta)
        zeta = (gamma - alpha) / (two * safe_beta)
        az = jnp.abs(zeta)
        # sqrt(1 + zeta^2) without overflowing zeta^2 (float16 overflows past |zeta| ~ 256).
        big = az > one
        inv = one / jnp.where(big, az, one)
        root = jnp.where(big, az * jnp.sqrt(one + inv * inv), jnp.sqrt(one + az * az))
        t = jnp.where(zeta >= 0, one, -one) / (az + root)
        cs = one / jnp.sqrt(one + t * t)
        sn = cs * t
        cs = jnp.where(skip, one, cs)
        sn = jnp.where(skip, zero, sn)

        def apply(x):
            xi, xj = x[:, i], x[:, j]
            new_i, new_j = cs * xi - sn * xj, sn * xi + cs * xj
            x = jnp.where((colid == i)[None, :], new_i[:, None], x)
            return jnp.where((colid == j)[None, :], new_j[:, None], x)

        return apply(b), apply(v), rotated | ~skip

    def sweep_cond(carry):
        _, _, rotated, sweeps = carry
        return rotated & (sweeps < max_sweeps)

    def sweep(carry):
        b, v, _, sweeps = carry
        b, v, rotated = lax.fori_loop(0, npairs, rotate, (b, v, jnp.zeros((), bool)))
        return b, v, rotated, sweeps + 1

    init = (a, jnp.eye(n, dtype=dtype), jnp.asarray(npairs > 0), jnp.zeros((), jnp.int32))
    b, v, _, _ = lax.while_loop(sweep_cond, sweep, init)
    s = norm2(b, axis=0)
    good = jnp.isfinite(s) & (s > 0)
    u = jnp.where(good[None, :], b / jnp.where(good, s, one)[None, :], zero)
    return u, s, v
