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
import math

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array

from .._precision import as_dtype, eps, sumsq
from ._qr import QRState, jacobi_svd, lu_solve, pivoted_lstsq, upper_solve

__all__ = [
    "AbstractFit",
    "WeightedQR",
    "IncrementalQR",
    "PivotedQR",
    "TruncatedSVD",
    "NormalEquationsFit",
    "ridged_lstsq",
    "guarded_solve",
]


def _check_rtol(rtol):
    if rtol is None:
        return None
    if isinstance(rtol, bool) or not isinstance(rtol, int | float):
        raise ValueError(f"rtol must be a real number or None, got {rtol!r}")
    rtol = float(rtol)
    if not (math.isfinite(rtol) and 0 <= rtol < 1):
        raise ValueError(f"rtol must lie in [0, 1), got {rtol!r}")
    return rtol


def _default_rtol(rtol, dtype, num_rows, ncols) -> Array:
    """`rtol` in `dtype`, or the default `eps max(4, min(M, k))` (the pinv-style cut)."""
    if rtol is not None:
        return as_dtype(rtol, dtype)
    dim = jnp.maximum(4, jnp.minimum(ncols, num_rows)).astype(dtype)
    return dim * eps(dtype)


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


class IncrementalQR(AbstractFit):
    """Reuse the greedy loop's incremental QR: `x = R^-1 Q^T y`, `O(M k)` per step.

    Equal to `WeightedQR` up to rounding as long as the factorisation is well conditioned; it
    shares `Q` with `OrthogonalProjection` (together, the cheap and stable pairing). A zero
    diagonal of `R` (which the QR append never produces for an accepted column) gives a
    non-finite solution and hence the ridged fallback.
    """

    def solve(self, design, target, qr, ncols):
        del design
        live = jnp.arange(qr.r.shape[0]) < ncols
        return upper_solve(qr.r, qr.q.T @ target, live)

    @property
    def label(self) -> str:
        return "incqr"


class PivotedQR(AbstractFit):
    """Rank-revealing Householder QR with column pivoting, solved from scratch each step.

    Like `WeightedQR`, but with the pinv-style rank cut: the factorisation stops at the
    first pivot `|alpha| <= rtol |alpha_0|`, and dependent columns get zero coefficients.

    **Arguments:**

    - `rtol`: the relative cut (a Python float), or `None` (default) for
        `eps(T) max(4, min(M, k))`.
    """

    rtol: float | None = eqx.field(static=True, default=None, converter=_check_rtol)

    def solve(self, design, target, qr, ncols):
        del qr
        rtol = _default_rtol(self.rtol, design.dtype, design.shape[0], ncols)
        return pivoted_lstsq(design, target, rtol)

    @property
    def label(self) -> str:
        return "pivqr"


class TruncatedSVD(AbstractFit):
    """Truncated pseudo-inverse from a one-sided Jacobi SVD: the minimum-norm solution.

    `x = sum_j (u_j^T y / s_j) v_j` over the singular values `s_j > rtol max(s)`; zeros if
    `max(s)` is zero or not finite. On a (nearly) duplicated pair of columns it spreads the
    weight over both, with the same residual as `PivotedQR` and a smaller `||x||`. The most
    robust fit at every precision. The cut is deliberately far below `sqrt(eps)`: a gain
    floor of `sqrt(eps)` in the selection admits directions that small.

    **Arguments:**

    - `rtol`: the relative cut (a Python float), or `None` (default) for
        `eps(T) max(4, min(M, k))`.
    """

    rtol: float | None = eqx.field(static=True, default=None, converter=_check_rtol)

    def solve(self, design, target, qr, ncols):
        del qr
        dtype = design.dtype
        zero = as_dtype(0, dtype)
        rtol = _default_rtol(self.rtol, dtype, design.shape[0], ncols)
        u, s, v = jacobi_svd(design)
        finite = jnp.isfinite(s)
        smax = jnp.max(jnp.where(finite, s, zero))
        ok = jnp.all(finite) & (smax > 0)
        keep = finite & (s > rtol * smax)
        coeff = jnp.where(keep, (u.T @ target) / jnp.where(keep, s, as_dtype(1, dtype)), zero)
        return jnp.where(ok, v @ coeff, jnp.zeros_like(coeff))

    @property
    def label(self) -> str:
        return "tsvd"


class NormalEquationsFit(AbstractFit):
    """The normal equations `(A^T A + lam I) x = A^T y`, solved by LU: a baseline only.

    Squares the condition number of the design, so that it needs float64 on an ill-conditioned
    design. With `ridge`, `lam = 100 eps tr(A^T A) / k` (the eps of the solve dtype).
    An exactly zero pivot makes the solve non-finite and so falls back to the ridged
    least squares.

    **Arguments:**

    - `ridge`: add the Tikhonov term (default `True`).
    - `island`: solve in float64 and round the result back to the working dtype (default
        `False`). This deliberately breaks the precision discipline (it reproduces the
        reference's arithmetic) and needs `jax_enable_x64`; otherwise tracing the fit raises
        `ValueError`.
    """

    ridge: bool = eqx.field(static=True, default=True)
    island: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        for name in ("ridge", "island"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"NormalEquationsFit {name} must be a bool")

    def solve(self, design, target, qr, ncols):
        del qr
        dtype = design.dtype
        if self.island:
            if not jax.config.jax_enable_x64:
                raise ValueError(
                    "NormalEquationsFit(island=True) solves in float64, which needs "
                    "jax.config.update('jax_enable_x64', True)"
                )
            design = design.astype(jnp.float64)
            target = target.astype(jnp.float64)
        sdtype = design.dtype
        k = design.shape[1]
        used = jnp.arange(k) < ncols
        gram = design.T @ design
        rhs = design.T @ target
        if self.ridge:
            count = jnp.maximum(ncols, 1).astype(sdtype)
            lam = as_dtype(100, sdtype) * eps(sdtype) * jnp.trace(gram) / count
            gram = gram + jnp.diag(jnp.where(used, lam, as_dtype(0, sdtype)))
        # Unused slots: an identity block with a zero right-hand side (zero coefficients).
        eye = jnp.eye(k, dtype=bool)
        both = used[:, None] & used[None, :]
        gram = jnp.where(both, gram, jnp.where(eye, as_dtype(1, sdtype), as_dtype(0, sdtype)))
        rhs = jnp.where(used, rhs, as_dtype(0, sdtype))
        return lu_solve(gram, rhs).astype(dtype)

    @property
    def label(self) -> str:
        return "normaleq" + ("+ridge" if self.ridge else "") + ("+f64" if self.island else "")


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
