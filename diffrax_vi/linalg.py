"""Dense linear algebra in the working precision.

LAPACK has no half precision, so below 32 bits the factorisations run in float32
(`precision.lapack_dtype`) and only the results are rounded back to the working dtype: a float16
run stays float16 at every interface.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .precision import lapack_dtype

__all__ = ["solve", "damped_least_squares"]


def solve(matrix: Array, rhs: Array) -> Array:
    """`matrix⁻¹ rhs` in the dtype of `rhs`."""
    dtype = jnp.result_type(rhs)
    work = lapack_dtype(dtype)
    return jnp.linalg.solve(matrix.astype(work), rhs.astype(work)).astype(dtype)


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
