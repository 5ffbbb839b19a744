"""The interface every ansatz implements."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array


class AbstractBasis(eqx.Module):
    """A family of curves `q_h(τ; θ)` on the unit step `τ ∈ [0, 1]`, one per degree of freedom.

    Parameters are an array `θ` of shape `(num_params, D)`: column `d` parametrises the curve
    of coordinate `d` (the networks of different coordinates share nothing).
    """

    def num_params(self) -> int:
        """Number of parameters of the curve of one coordinate."""
        raise NotImplementedError

    def evaluate(self, theta: Array, tau) -> Array:
        """`q_h(τ; θ)`, shape `(D,)`."""
        raise NotImplementedError

    def value_and_derivative(self, theta: Array, tau) -> tuple[Array, Array]:
        """`(q_h(τ), dq_h/dτ)` at one `τ`, each of shape `(D,)`."""
        tau = jnp.asarray(tau, theta.dtype)
        return jax.jvp(lambda s: self.evaluate(theta, s), (tau,), (jnp.ones_like(tau),))

    def advance(self, theta: Array, ratio) -> Array:
        """Parameters of the continued curve on the next step.

        Returns `θ'` with `q_h(τ; θ') = q_h(1 + ratio·τ; θ)`: the curve of this step carried
        past its end, in the local time of a next step whose length is `ratio` times this one.
        """
        raise NotImplementedError

    def check(self, dtype) -> None:
        """Raise `ValueError` if the ansatz cannot work in `dtype`."""
