"""Refits of the output weights on the columns selected so far.

After every accepted atom the greedy loop solves the weighted least-squares problem
`min_x ||A x - y||` for *all* selected columns (the "orthogonal" in orthogonal greedy).
`A` is the `(M, K)` design in scaled units with zero columns at unused slots, `y` the scaled
target. Every fit runs through `guarded_solve`, which guarantees a finite result with zero
coefficients at unused slots: a non-finite solution falls back to a ridged least-squares
solve, and a non-finite ridged solution to zeros.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array

from .numerics import as_dtype, eps, sumsq
from .qr import QRState, pivoted_lstsq

__all__ = ["AbstractFit", "WeightedQR", "ridged_lstsq", "guarded_solve"]


class AbstractFit(eqx.Module):
    """Base class of the output-weight refits.

    Subclasses implement `solve`; they need not worry about non-finite results or unused
    columns, which `guarded_solve` handles.
    """

    @abc.abstractmethod
    def solve(
        self,
        design: Array,
        target: Array,
        qr: QRState,
        ncols: Array,
    ) -> Array:
        """Least-squares coefficients of the first `ncols` columns of `design`.

        **Arguments:**

        - `design`: the scaled design; columns at positions `>= ncols` are zero.
        - `target`: the scaled target.
        - `qr`: the incremental QR factors of the same columns (for fits that reuse them).
        - `ncols`: number of selected columns (an int32 scalar, at least one).
        """

    @property
    def label(self) -> str:
        """A short name used in configuration labels."""
        return type(self).__name__


class WeightedQR(AbstractFit):
    """Column-pivoted Householder QR of the design, solved from scratch at every step.

    The conditioning is that of the design itself (not its square, as with normal equations).
    The rank cut is `min(M, k) eps` relative to the first pivot; a column beyond the numerical
    rank gets a zero coefficient.
    """

    def solve(self, design, target, qr, ncols):
        del qr
        dtype = design.dtype
        m = design.shape[0]
        kk = jnp.minimum(ncols, m).astype(dtype)
        return pivoted_lstsq(design, target, kk * eps(dtype))

    @property
    def label(self) -> str:
        return "qr"


def ridged_lstsq(
    design: Array,
    target: Array,
    ncols: Array,
    factor: float = 100.0,
) -> Array:
    """Tikhonov-regularised least squares, the shared last resort of every fit.

    Solves `[A; sqrt(lam) I] x ≈ [y; 0]` by pivoted QR (never by normal equations), with
    `lam = factor * eps * ||A||_F^2 / ncols` (`factor * eps` times the mean squared column
    norm); if that is not a positive finite number, `lam = eps`. The identity block covers only
    the selected columns, so unused (zero) columns keep a zero coefficient. Returns zeros if
    the regularised solve is itself not finite.

    **Arguments:**

    - `design`: the `(M, K)` scaled design with zero columns at positions `>= ncols`.
    - `target`: the `(M,)` scaled target.
    - `ncols`: number of selected columns.
    - `factor`: the multiple of `eps` (default `100`).
    """
    dtype = design.dtype
    k = design.shape[1]
    e = eps(dtype)
    count = jnp.maximum(ncols, 1).astype(dtype)
    lam = as_dtype(factor, dtype) * e * sumsq(design) / count
    lam = jnp.where(jnp.isfinite(lam) & (lam > 0), lam, e)
    used = (jnp.arange(k) < ncols).astype(dtype)
    augmented = jnp.concatenate([design, jnp.diag(jnp.sqrt(lam) * used)], axis=0)
    rhs = jnp.concatenate([target, jnp.zeros((k,), dtype)])
    x = pivoted_lstsq(augmented, rhs, as_dtype(max(4, k), dtype) * e)
    return jnp.where(jnp.all(jnp.isfinite(x)), x, jnp.zeros_like(x))


def guarded_solve(
    fit: AbstractFit,
    design: Array,
    target: Array,
    qr: QRState,
    ncols: Array,
) -> Array:
    """Run `fit` and make its result safe: finite, and zero at unused columns.

    A result with any non-finite entry is replaced by `ridged_lstsq` (which in turn returns
    zeros when it fails); the fallback is only evaluated when needed (under `vmap` both
    branches run).
    """
    used = jnp.arange(design.shape[1]) < ncols
    x = fit.solve(design, target, qr, ncols)
    x = jnp.where(used, x, jnp.zeros_like(x))
    x = lax.cond(
        jnp.all(jnp.isfinite(x)),
        lambda: x,
        lambda: ridged_lstsq(design, target, ncols),
    )
    return jnp.where(used, x, jnp.zeros_like(x))
