"""Dense output of a network step: the converged ansatz itself."""

from __future__ import annotations

import functools
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, PyTree

from ._ansatz.base import AbstractBasis
from ._lagrange import lagrange_weights

__all__ = ["NetworkInterpolation"]


@functools.cache
def _gauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


class NetworkInterpolation(diffrax.AbstractLocalInterpolation):
    """The trajectory of one accepted step, as `sol.evaluate(t)` sees it.

    Position: the converged curve of the step as the formulation builds it from the ansatz;
    exact at both step ends (for free endpoints a linear term of the size of the Newton
    tolerance makes the curve hit `q_n`).

    Momentum: the balance `ṗ = f` integrated along the step, `p(τ) = p_n + h ∫_0^τ F(s) ds`,
    where `F` is the polynomial through the forces `f(t_j, Q_j, V_j)` of the converged curve at
    the quadrature nodes, plus the linear term that makes it end exactly at `p_{n+1}`. Forces
    depend mostly on positions, which the converged curve carries accurately, so this is
    more accurate than evaluating the momentum map on the curve's velocity. Its time
    derivative is the force polynomial itself.
    """

    t0: ArrayLike
    t1: ArrayLike
    theta: PyTree
    q0: Array
    q1: Array
    p0: Array
    p1: Array
    f_nodes: Array
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
        p = self._momentum(tau)
        # A failed step's curve is NaN, but its start is the accepted state (diffrax saves
        # `t0` from the first step's interpolation). Successful steps are left alone, so
        # derivatives at a step's start are those of the curve.
        start = tau == 0
        q = jnp.where(start & ~jnp.all(jnp.isfinite(q)), self.q0, q)
        p = jnp.where(start & ~jnp.all(jnp.isfinite(p)), self.p0, p)
        return q, p

    def _momentum(self, tau: Array) -> Array:
        dtype = self.p0.dtype
        h = jnp.asarray(self.h_step, dtype)
        gauss, weights = _gauss(len(self.nodes))
        # ∫_0^τ F = τ Σ_k w_k F(τ x_k): exact for the degree R − 1 force polynomial.
        at = jax.vmap(lambda x: lagrange_weights(self.nodes, tau * x))(jnp.asarray(gauss, dtype))
        partial = tau * (jnp.asarray(weights, dtype) @ at) @ self.f_nodes
        whole = jnp.asarray(weights, dtype) @ self.f_nodes  # ∫_0^1 F (Gauss rule, exact)
        # The Lagrange weights at τ = 1 reproduce `whole` only up to rounding: pin the value
        # there (a correction of rounding size, so the τ-derivative is left as it is).
        gap = jax.lax.stop_gradient(whole - partial)
        partial = partial + jnp.where(tau == 1, gap, jnp.zeros_like(gap))
        # p_n + hP(τ) + τ (p_{n+1} − p_n − hW), written so that both ends are exact in floats.
        return (1 - tau) * (self.p0 + h * partial) + tau * (self.p1 - h * (whole - partial))
