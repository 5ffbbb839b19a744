"""Two-hidden-layer network ansatz (the reference's `DenseNetBasis`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from .._activations import activation_name, check_activation
from .base import AbstractBasis
from .shallow import network_min_nodes

__all__ = ["DenseNetBasis"]


def _check_width(name: str, value) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")


class DenseNetBasis(AbstractBasis):
    """`q_h(τ) = Σ_{k=1..S₂} γ_k σ(Σ_{i=1..S₁} A_{ki} σ(a_i τ + e_i) + g_k)` per coordinate.

    A fully connected network `1 → S₁ → S₂ → 1` with the activation on both hidden layers and a
    linear output layer without bias. Like `ShallowNetBasis` it does not pass through
    prescribed endpoints, so it is used with the free-endpoint formulation (continuity is an
    equation of the step).

    Parameters of coordinate `d` (column `θ[:, d]`, `NP = 2S₁ + S₂S₁ + 2S₂` entries), in the
    reference's order:

    `[a_1..a_{S₁} | e_1..e_{S₁} | A[:, 1] | A[:, 2] | .. | A[:, S₁] | g_1..g_{S₂} | γ_1..γ_{S₂}]`

    i.e. the `S₂ × S₁` matrix `A` stored column by column. `split` and `join` convert between
    this flat layout and the separate layers.

    **Arguments:**

    - `activation`: elementwise `σ` of both hidden layers, e.g. `diffrax_vi.tanh`. It must be
      smooth (the Newton Jacobian differentiates it three times) and keep the dtype of its
      input.
    - `width1`: number of neurons `S₁` of the first hidden layer.
    - `width2`: number of neurons `S₂` of the second hidden layer.
    - `derivatives`: `"autodiff"` (default) or `"sympy"`: the curve and its first derivatives
      in the parameters and in `τ` taken by sympy (one expression, common subexpressions
      shared) and compiled to JAX once; see `ShallowNetBasis`.
    """

    activation: Callable = eqx.field(static=True)
    width1: int = eqx.field(static=True)
    width2: int = eqx.field(static=True)
    derivatives: str = eqx.field(static=True, default="autodiff")

    can_advance: ClassVar[bool] = True

    def __check_init__(self):
        if not callable(self.activation):
            raise TypeError(f"activation must be callable, got {type(self.activation).__name__}")
        _check_width("width1", self.width1)
        _check_width("width2", self.width2)
        if self.derivatives not in ("autodiff", "sympy"):
            raise ValueError(
                f"derivatives must be 'autodiff' or 'sympy', got {self.derivatives!r}"
            )
        if self.derivatives == "sympy":
            from .._codegen import sympy_activation  # sympy only when asked for

            sympy_activation(self.activation)

    def num_params(self) -> int:
        s1, s2 = self.width1, self.width2
        return 2 * s1 + s2 * s1 + 2 * s2

    def split(self, theta: Array) -> tuple[Array, Array, Array, Array, Array]:
        """The layers `(a, e, A, g, γ)` of parameters `θ`.

        For `θ` of shape `(NP, D)` they have shapes `(S₁, D)`, `(S₁, D)`, `(S₂, S₁, D)`,
        `(S₂, D)`, `(S₂, D)`; a single column `(NP,)` gives the same without the trailing `D`.
        """
        s1, s2 = self.width1, self.width2
        if theta.shape[0] != self.num_params():
            raise ValueError(
                f"{self!r} has {self.num_params()} parameters per coordinate; got an array of "
                f"shape {theta.shape}"
            )
        rest = theta.shape[1:]
        a = theta[:s1]
        e = theta[s1 : 2 * s1]
        end_a = 2 * s1 + s1 * s2
        # Column-major: the flat block holds A[:, 0], A[:, 1], ..., each of length S₂.
        big_a = jnp.moveaxis(theta[2 * s1 : end_a].reshape((s1, s2) + rest), 0, 1)
        g = theta[end_a : end_a + s2]
        gamma = theta[end_a + s2 :]
        return a, e, big_a, g, gamma

    @staticmethod
    def join(a: Array, e: Array, big_a: Array, g: Array, gamma: Array) -> Array:
        """Flat parameters from the layers `(a, e, A, g, γ)` (shapes as returned by `split`)."""
        s2, s1 = big_a.shape[:2]
        flat_a = jnp.moveaxis(big_a, 0, 1).reshape((s1 * s2,) + big_a.shape[2:])
        return jnp.concatenate([a, e, flat_a, g, gamma], axis=0)

    def hidden(self, theta: Array, tau) -> Array:
        """Outputs `σ(A σ(a τ + e) + g)` of the second hidden layer at one `τ`, shape
        `(S₂, D)` (or `(S₂,)` for a single column)."""
        a, e, big_a, g, _ = self.split(theta)
        first = self.activation(a * tau + e)
        return self.activation(jnp.einsum("ki...,i...->k...", big_a, first) + g)

    def evaluate(self, theta, tau):
        if self.derivatives == "sympy":
            from .sympy_kernels import symbolic_dense_evaluate

            return symbolic_dense_evaluate(self)(theta, tau)
        gamma = self.split(theta)[4]
        return jnp.sum(gamma * self.hidden(theta, tau), axis=0)

    def advance(self, theta, ratio):
        # Only the first layer sees τ: a(1 + ρτ) + e = (ρa)τ + (a + e).
        a, e, big_a, g, gamma = self.split(theta)
        return self.join(a * ratio, e + a, big_a, g, gamma)

    def check(self, dtype) -> None:
        check_activation(self.activation, dtype)

    def min_nodes(self) -> int:
        return network_min_nodes(self.width2)

    def __repr__(self):
        return (
            f"DenseNetBasis({activation_name(self.activation)}, width1={self.width1}, "
            f"width2={self.width2})"
        )
