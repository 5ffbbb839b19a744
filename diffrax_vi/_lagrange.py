"""Lagrange interpolation through fixed points on the step: the polynomial ansatz's basis
and the dense output's reconstruction from the quadrature nodes."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

__all__ = ["continuation_coefficients", "lagrange_values_and_slopes", "lagrange_weights"]


@functools.cache
def _barycentric(points: tuple[float, ...]) -> np.ndarray:
    x = np.asarray(points)
    diff = x[:, None] - x[None, :]
    np.fill_diagonal(diff, 1.0)
    return 1.0 / np.prod(diff, axis=1)


def lagrange_weights(points: tuple[float, ...], tau: Array) -> Array:
    """Values at `tau` of the Lagrange basis polynomials through `points` (first-form formula,
    exact at the points themselves)."""
    dtype = jnp.result_type(tau)
    # constants as NumPy arrays: nothing to compile where they are evaluated eagerly
    x = np.asarray(points, dtype)
    w = _barycentric(points).astype(dtype)
    diff = tau - x
    n = len(points)
    # ℓ_k(τ) = w_k Π_{m≠k} (τ − x_m): a product over the other points, no division by zero.
    others = jnp.where(np.eye(n, dtype=bool), np.ones((), dtype), diff[None, :])
    values = w * jnp.prod(others, axis=1)
    # At a point the rounded weight times the product can miss 1 by an ulp, which would
    # scale the state by 1 ± eps on every step (a linear energy drift): there the values are
    # exactly one-hot, with the derivative of the formula (`v − stop_gradient(v)` is zero).
    at = diff == 0
    exact = jnp.where(jnp.any(at), at.astype(dtype), values)
    return jax.lax.stop_gradient(exact) + (values - jax.lax.stop_gradient(values))


def lagrange_values_and_slopes(points: tuple[float, ...], taus: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
    """The Lagrange basis through `points` and its τ-derivative at the points `taus`
    (`(len(taus), len(points))` each), in NumPy float64: the first-form formula and its
    product rule (no division by `τ − x_m`), exactly one-hot at the points themselves."""
    x = np.asarray(points, np.float64)
    taus = np.asarray(taus, np.float64)
    n = len(x)
    w = _barycentric(tuple(points))
    diff = taus[:, None] - x[None, :]  # (K, n)
    values = np.empty((len(taus), n))
    slopes = np.zeros((len(taus), n))
    for k in range(n):
        others = [m for m in range(n) if m != k]
        values[:, k] = w[k] * np.prod(diff[:, others], axis=1)
        for j in others:
            rest = [m for m in others if m != j]
            slopes[:, k] += w[k] * np.prod(diff[:, rest], axis=1)
    at = diff == 0
    hit = np.any(at, axis=1)
    values[hit] = at[hit].astype(np.float64)
    return values, slopes


@functools.cache
def continuation_coefficients(points: tuple[float, ...]) -> np.ndarray:
    """`C` (`(n, n, n)`) with `Σ_m r^m C[m, j, k] = ℓ_k(1 + r τ_j)`: the Lagrange basis through
    `points` at the points of a next step `r` times as long, continued from this one, as a
    polynomial in `r` (NumPy float64; evaluate it by Horner's rule: a few fused products
    instead of a product over the points for every entry). A row of `τ_j = 0` (this step's
    end, where it is a point) is exactly one-hot."""
    x = np.asarray(points, np.float64)
    n = len(x)
    weights = _barycentric(tuple(points))
    coefficients = np.zeros((n, n, n))
    for j in range(n):
        for k in range(n):
            poly = np.array([weights[k]])  # ascending powers of r
            for m in range(n):
                if m != k:  # the factor (1 − τ_m) + τ_j r
                    poly = np.convolve(poly, np.array([1.0 - x[m], x[j]]))
            coefficients[: len(poly), j, k] = poly
    for j in np.flatnonzero(x == 0.0):
        coefficients[:, j, :] = 0.0
        coefficients[0, j, :] = (x == 1.0).astype(np.float64)
    return coefficients
