"""Polynomial ansatz in Lagrange form: classical continuous-Galerkin variational integrators."""

from __future__ import annotations

import functools
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._lagrange import continuation_coefficients, lagrange_values_and_slopes, lagrange_weights
from .._quadrature import gauss_lobatto_upper, symmetric_points
from .base import AbstractBasis

__all__ = ["LagrangeBasis", "lobatto_points"]


@functools.cache
def lobatto_points(degree: int) -> tuple[float, ...]:
    """The `degree + 1` Gauss–Lobatto points on `[0, 1]`: both ends and the roots of
    `P'_degree` (well-conditioned interpolation points that include the step ends).

    Computed in extended precision and rounded to float64 so that the points are exactly
    symmetric about 1/2 (`τ_k + τ_{degree-k} == 1`)."""
    if degree == 1:
        return (0.0, 1.0)
    upper = gauss_lobatto_upper(degree)
    points = symmetric_points(upper, np.float64, middle=degree % 2 == 0, ends=True)
    return tuple(float(v) for v in points)


class LagrangeBasis(AbstractBasis):
    """`q_h(τ) = Σ_k θ_k ℓ_k(τ)`: the polynomial of degree `s` through the values `θ_k` at
    `s + 1` points `τ_k` of the step (Lagrange basis polynomials `ℓ_k`).

    With free endpoints this is the classical continuous-Galerkin variational integrator
    (cGVI): it is linear in its parameters, so the seed is an exact least-squares fit, and a
    Gauss–Legendre rule with at least `s` nodes gives a method of order `2s`.

    **Arguments:**

    - `degree`: polynomial degree `s ≥ 1`.
    - `points`: `"lobatto"` (default; Gauss–Lobatto points, both ends included) or
      `"equispaced"` (`τ_k = k/s`).
    """

    degree: int = eqx.field(static=True)
    points: str = eqx.field(static=True, default="lobatto")

    can_advance: ClassVar[bool] = True
    linear: ClassVar[bool] = True
    coordinatewise: ClassVar[bool] = True

    def __check_init__(self):
        if not isinstance(self.degree, int) or isinstance(self.degree, bool) or self.degree < 1:
            raise ValueError(f"degree must be an integer >= 1, got {self.degree!r}")
        if self.points not in ("lobatto", "equispaced"):
            raise ValueError(f"points must be 'lobatto' or 'equispaced', got {self.points!r}")

    @property
    def control_points(self) -> tuple[float, ...]:
        if self.points == "lobatto":
            return lobatto_points(self.degree)
        return tuple(k / self.degree for k in range(self.degree + 1))

    def num_params(self) -> int:
        return self.degree + 1

    def min_nodes(self) -> int:
        # Each node shows the action the value and the slope of the curve; with `2R < s + 1`
        # the equations do not pin the polynomial down: the solve "converges" to one of many
        # curves and the step is wrong while reported as successful.
        return (self.degree + 2) // 2

    def evaluate(self, theta: Array, tau) -> Array:
        tau = jnp.asarray(tau, theta.dtype)
        return lagrange_weights(self.control_points, tau) @ theta

    def sample_matrices(self, taus) -> tuple[np.ndarray, np.ndarray]:
        return lagrange_values_and_slopes(self.control_points, np.asarray(taus, np.float64))

    def advance(self, theta: Array, ratio) -> Array:
        # Values of the same polynomial at the control points of the next step, `1 + r τ_j`:
        # the matrix of Lagrange values there is a polynomial in the ratio `r` with constant
        # coefficients, evaluated by Horner's rule (a few fused products, not a product over
        # the points for every entry).
        ratio = jnp.asarray(ratio, theta.dtype)
        coefficients = continuation_coefficients(self.control_points)
        matrix = jnp.asarray(coefficients[-1], theta.dtype)
        for c in coefficients[-2::-1]:
            matrix = matrix * ratio + c.astype(theta.dtype)
        return matrix @ theta

    def __repr__(self):
        return f"LagrangeBasis(degree={self.degree}, points={self.points!r})"
