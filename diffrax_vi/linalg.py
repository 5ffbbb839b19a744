"""Dense linear algebra in the working precision.

LAPACK has no half precision, so below 32 bits the factorisations run in float32 and only the
results are rounded back to the working dtype: a float16 run stays float16 at every interface.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["solve", "damped_least_squares"]


def _work_dtype(dtype):
    return jnp.float32 if jnp.finfo(dtype).bits < 32 else dtype


def solve(matrix: Array, rhs: Array) -> Array:
    """`matrix⁻¹ rhs` in the dtype of `rhs`."""
    dtype = jnp.result_type(rhs)
    work = _work_dtype(dtype)
    return jnp.linalg.solve(matrix.astype(work), rhs.astype(work)).astype(dtype)


def damped_least_squares(matrix: Array, rhs: Array, sqrt_mu: Array) -> Array:
    """`argmin_d ‖matrix·d − rhs‖² + μ‖d‖²`, by QR of `[matrix; √μ I]` (no normal equations)."""
    dtype = jnp.result_type(rhs)
    work = _work_dtype(dtype)
    n = matrix.shape[1]
    augmented = jnp.concatenate(
        [matrix.astype(work), sqrt_mu.astype(work) * jnp.eye(n, dtype=work)], axis=0
    )
    stacked = jnp.concatenate([rhs.astype(work), jnp.zeros(n, work)])
    qmat, rmat = jnp.linalg.qr(augmented)
    return jax.scipy.linalg.solve_triangular(rmat, qmat.T @ stacked).astype(dtype)
