"""The working precision: one vocabulary for every module.

A solve runs in the dtype `T` of its state. Thresholds are written as multiples of `eps(T)` or
`sqrt(eps(T))`, never as absolute numbers, so that the same code means the same in float16,
float32 and float64; constants enter through `as_dtype`. LAPACK has no half precision, so
factorisations run in `lapack_dtype(T)` (float32 below 32 bits) and their results are rounded
back to `T`.
"""

from __future__ import annotations

import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

__all__ = [
    "eps",
    "sqrt_eps",
    "as_dtype",
    "floating_dtype",
    "lapack_dtype",
    "two_sum",
    "compensated_add",
    "sumsq",
    "norm2",
    "power_of_two_scale",
]


def eps(dtype) -> Array:
    """Machine epsilon of `dtype` (the spacing of floats at 1), as a scalar of that dtype."""
    return jnp.asarray(jnp.finfo(dtype).eps, dtype=dtype)


def sqrt_eps(dtype) -> Array:
    """The correctly rounded square root of `eps(dtype)`, as a scalar of that dtype.

    Computed once in NumPy float64 and rounded to `dtype`; the same value a square root in
    `dtype` would give, because both are correctly rounded.
    """
    return jnp.asarray(np.sqrt(np.float64(jnp.finfo(dtype).eps)), dtype=dtype)


def as_dtype(value, dtype) -> Array:
    """`value` (a Python number or array) as a `dtype` array: the one way constants enter."""
    return jnp.asarray(value, dtype=dtype)


def lapack_dtype(dtype) -> np.dtype:
    """The dtype a factorisation of `dtype` data runs in: float32 below 32 bits, else `dtype`."""
    return np.dtype(jnp.float32) if jnp.finfo(dtype).bits < 32 else np.dtype(dtype)


def floating_dtype(*values) -> np.dtype:
    """The common floating dtype of `values` (the default float if none is floating)."""
    dtype = jnp.result_type(*values) if values else jnp.dtype(float)
    if not jnp.issubdtype(dtype, jnp.inexact):
        dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
    return np.dtype(dtype)


def sumsq(x: Array, axis=None) -> Array:
    """Sum of squares, accumulated in the dtype of `x`."""
    return jnp.sum(x * x, axis=axis)


def norm2(x: Array, axis=None) -> Array:
    """Euclidean norm as `sqrt(sum(x**2))` in the dtype of `x` (no widening rescale)."""
    return jnp.sqrt(sumsq(x, axis=axis))


_INT_FOR_FLOAT = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}


def power_of_two_scale(largest: Array) -> Array:
    """The power of two `2**-E` that maps `largest = f * 2**E` (`1 <= f < 2`) into `[1, 2)`.

    The factor is assembled from its exponent bits, so it is an exact power of two and
    multiplying by it only shifts exponents. It is `1` whenever the rescale is impossible or
    pointless: `largest` zero, negative or non-finite, or `2**-E` outside the normal range of
    the dtype (e.g. float16 when `largest` is below `2**-14`).

    **Arguments:**

    - `largest`: a non-negative scalar, typically the largest finite atom norm.
    """
    dtype = largest.dtype
    info = jnp.finfo(dtype)
    nmant = int(info.nmant)
    bias = int(info.maxexp) - 1
    int_dtype = _INT_FOR_FLOAT[np.dtype(dtype).itemsize]
    one = as_dtype(1, dtype)
    _, e = jnp.frexp(largest)  # largest = m * 2**e with m in [0.5, 1)
    biased = bias - (e.astype(jnp.int32) - 1)  # biased exponent of 2**-(e - 1)
    in_range = (biased >= 1) & (biased <= 2 * bias)
    safe = jnp.where(in_range, biased, bias).astype(int_dtype)
    bits = lax.shift_left(safe, jnp.asarray(nmant, int_dtype))
    scale = lax.bitcast_convert_type(bits, dtype)
    ok = in_range & jnp.isfinite(largest) & (largest > 0)
    return jnp.where(ok, scale, one)


def two_sum(a: Array, b: Array) -> tuple[Array, Array]:
    """`(s, e)` with `s = fl(a + b)` and `a + b = s + e` exactly (Knuth's TwoSum: no
    condition on the sizes of `a` and `b`)."""
    s = a + b
    b_part = s - a
    a_part = s - b_part
    return s, (a - a_part) + (b - b_part)


def compensated_add(x: Array, dx: Array, carried: Array) -> tuple[Array, Array]:
    """`x + dx` by compensated summation: the rounding `carried` from the last sum is added to
    the increment, and the rounding of this sum is returned to be carried to the next."""
    return two_sum(x, dx.astype(x.dtype) + carried)
