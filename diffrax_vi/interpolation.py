"""Dense output of a network step: the converged ansatz itself."""

from __future__ import annotations

import functools
from typing import Any

import diffrax
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, PyTree

from .ansatz.base import AbstractBasis

__all__ = ["NetworkInterpolation", "lagrange_weights"]


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
    x = jnp.asarray(points, dtype)
    w = jnp.asarray(_barycentric(points), dtype)
    diff = tau - x
    n = len(points)
    # ℓ_k(τ) = w_k Π_{m≠k} (τ − x_m): a product over the other points, no division by zero.
    others = jnp.where(np.eye(n, dtype=bool), jnp.ones((), dtype), diff[None, :])
    return w * jnp.prod(others, axis=1)


class NetworkInterpolation(diffrax.AbstractLocalInterpolation):
    """The trajectory of one accepted step, as `sol.evaluate(t)` sees it.

    Position: the converged curve of the step as the formulation builds it from the ansatz;
    exact at both step ends (for free endpoints a linear term of the size of the Newton
    tolerance makes the curve hit `q_n`). Momentum: the polynomial through `p_n` at `τ = 0`,
    the momenta `ϑ(t_j, Q_j, V_j)` of the converged curve at the quadrature nodes, and
    `p_{n+1}` at `τ = 1`: exact at step ends and accurate to the order of the step inside.
    """

    t0: ArrayLike
    t1: ArrayLike
    theta: PyTree
    q0: Array
    q1: Array
    p0: Array
    p1: Array
    p_nodes: Array
    t_step: Array
    h_step: Array
    basis: AbstractBasis = eqx.field(static=True)
    formulation: Any = eqx.field(static=True)
    nodes: tuple[float, ...] = eqx.field(static=True)

    def evaluate(self, t0, t1=None, left: bool = True):
        del left
        if t1 is not None:
            return jtu.tree_map(lambda a, b: a - b, self.evaluate(t1), self.evaluate(t0))
        dtype = self.q0.dtype
        tau = jnp.asarray((t0 - self.t0) / (self.t1 - self.t0), dtype)
        basis = self.basis.at_step(self.t_step, self.h_step)
        q = self.formulation.dense_position(basis, self.theta, self.q0, self.q1, tau)
        points = (0.0,) + self.nodes + (1.0,)
        values = jnp.concatenate([self.p0[None], self.p_nodes, self.p1[None]], axis=0)
        p = lagrange_weights(points, tau) @ values
        return q, p
