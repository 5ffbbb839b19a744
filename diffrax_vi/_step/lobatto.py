"""The Gauss–Lobatto rule of the constrained step: its points, weights and differentiation
matrix, shared by the general solve (`holonomic`) and the split iteration
(`constrained_engine`)."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from .._ansatz.polynomial import lobatto_points

__all__ = ["lobatto_arrays", "lobatto_rule"]


@functools.cache
def lobatto_rule(degree: int) -> tuple[tuple[float, ...], np.ndarray, np.ndarray]:
    """`(points, weights, D)` of the Gauss–Lobatto rule with `degree + 1` points on `[0, 1]`:
    the points (`lobatto_points`), their quadrature weights and the differentiation matrix
    `D_ij = ℓ_j'(τ_i)` of the Lagrange polynomials through them. Weights and derivatives are
    computed in extended precision from the float64 points and rounded once."""
    import mpmath

    points = lobatto_points(degree)
    n = len(points)
    with mpmath.workdps(40):
        x = [mpmath.mpf(p) for p in points]
        # ℓ_j(τ) = Π_{m≠j} (τ − x_m) / (x_j − x_m): integrate its monomial coefficients.
        weights, derivative = [], [[mpmath.mpf(0)] * n for _ in range(n)]
        for j in range(n):
            coefficients = [mpmath.mpf(1)]
            denominator = mpmath.mpf(1)
            for m in range(n):
                if m == j:
                    continue
                coefficients = [
                    (coefficients[k - 1] if k > 0 else 0)
                    - x[m] * (coefficients[k] if k < len(coefficients) else 0)
                    for k in range(len(coefficients) + 1)
                ]
                denominator *= x[j] - x[m]
            weights.append(sum(c / (k + 1) for k, c in enumerate(coefficients)) / denominator)
            for i in range(n):
                slope = sum(k * c * x[i] ** (k - 1) for k, c in enumerate(coefficients) if k)
                derivative[i][j] = slope / denominator
        w = np.array([float(v) for v in weights])
        d = np.array([[float(v) for v in row] for row in derivative])
    return points, w, d


def lobatto_arrays(degree: int, dtype):
    """`lobatto_rule`'s points, weights and differentiation matrix as arrays of `dtype`."""
    points, w, d = lobatto_rule(degree)
    return jnp.asarray(points, dtype), jnp.asarray(w, dtype), jnp.asarray(d, dtype)
