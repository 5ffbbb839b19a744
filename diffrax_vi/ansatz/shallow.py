"""Single-hidden-layer network ansatz (the reference's `ShallowNetBasis`)."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ..activations import activation_name, check_activation
from .base import AbstractBasis


class ShallowNetBasis(AbstractBasis):
    """`q_h(τ) = Σ_{i=1..S} α_i σ(w_i τ + β_i)` per coordinate, with no output bias.

    Parameters of coordinate `d` are the column `θ[:, d] = [α_1..α_S, w_1..w_S, β_1..β_S]`.
    A network does not pass through prescribed endpoints: the free-endpoint formulation adds
    continuity `q_h(0) = q_n` as an equation.

    **Arguments:**

    - `activation`: elementwise `σ`, e.g. `diffrax_vi.tanh` or `diffrax_vi.relu_k(3)`. It must
      be smooth enough for Newton (the Jacobian differentiates it three times) and keep the
      dtype of its input.
    - `width`: number of neurons `S` per coordinate.
    """

    activation: Callable = eqx.field(static=True)
    width: int = eqx.field(static=True)

    def __check_init__(self):
        if not callable(self.activation):
            raise TypeError(f"activation must be callable, got {type(self.activation).__name__}")
        if not isinstance(self.width, int) or isinstance(self.width, bool) or self.width < 1:
            raise ValueError(f"width must be a positive integer, got {self.width!r}")

    def num_params(self) -> int:
        return 3 * self.width

    def split(self, theta: Array) -> tuple[Array, Array, Array]:
        """`(α, w, β)`, each of shape `(S, D)`."""
        s = self.width
        return theta[:s], theta[s : 2 * s], theta[2 * s :]

    @staticmethod
    def join(alpha: Array, w: Array, beta: Array) -> Array:
        return jnp.concatenate([alpha, w, beta], axis=0)

    def evaluate(self, theta, tau):
        alpha, w, beta = self.split(theta)
        return jnp.sum(alpha * self.activation(w * tau + beta), axis=0)

    def advance(self, theta, ratio):
        alpha, w, beta = self.split(theta)
        return self.join(alpha, w * ratio, beta + w)

    def check(self, dtype) -> None:
        check_activation(self.activation, dtype)

    def __repr__(self):
        return f"ShallowNetBasis({activation_name(self.activation)}, width={self.width})"
