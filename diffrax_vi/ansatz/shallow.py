"""Single-hidden-layer network ansatz (the reference's `ShallowNetBasis`), optionally with
mirrored neuron pairs (the reference's reversible variants)."""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ..activations import activation_name, check_activation
from ..oga.symmetry import AbstractSymmetry, MirrorPairs, NoSymmetry, SharedMirrorPairs, mirror
from .base import AbstractBasis

__all__ = ["ShallowNetBasis"]


def _network_min_nodes(width: int) -> int:
    """Nodes a network with `width` output weights needs: each node shows the action the
    value and the slope of the curve, so `2R >= width`. Measured on the harmonic oscillator
    (5 steps of 0.1, tanh): width 10 fails with 1 to 4 Gauss nodes and works with 5. The rule
    only refuses what fails: width 4 with 2 nodes fails too, but loudly (a failed step)."""
    return (width + 1) // 2


def _interleave(a: Array, b: Array) -> Array:
    """Rows `a_0, b_0, a_1, b_1, ...` (along axis 0)."""
    return jnp.stack([a, b], axis=1).reshape((-1,) + a.shape[1:])


class ShallowNetBasis(AbstractBasis):
    """`q_h(τ) = Σ_{i=1..S} α_i σ(w_i τ + β_i)` per coordinate, with no output bias.

    A network does not pass through prescribed endpoints: the free-endpoint formulation adds
    continuity `q_h(0) = q_n` as an equation, the interpolating one multiplies the network by
    `τ(1 − τ)` and adds the chord.

    With a mirrored `symmetry` the neurons come in pairs `(w, β)` and `(−w, w + β)`; the second
    neuron `σ(w(1 − τ) + β)` is the first reflected about `τ = 1/2`, so the family of curves
    is closed under time reversal of the step. Only the first neuron of each pair has free
    hidden parameters, and the solve differentiates through the mirror map (the residual is
    the exact gradient of the action on the reduced family). Parameter layout of coordinate
    `d` (column `θ[:, d]`):

    - `NoSymmetry()`: `[α_1..α_S, w_1..w_S, β_1..β_S]` (`3S` parameters);
    - `MirrorPairs()`: `[α_1..α_S, w_1, w_3, .., w_{S−1}, β_1, β_3, .., β_{S−1}]` (`2S`),
      every neuron with its own output weight;
    - `SharedMirrorPairs()`: `[α_1, α_3, .., α_{S−1}, w_1, w_3, .., β_1, β_3, ..]` (`3S/2`),
      one output weight per pair, shared in the solve itself.

    **Arguments:**

    - `activation`: elementwise `σ`, e.g. `diffrax_vi.tanh` or `diffrax_vi.relu_k(3)`. It must
      be smooth enough for Newton (the Jacobian differentiates it three times) and keep the
      dtype of its input.
    - `width`: number of neurons `S` per coordinate (even with a mirrored symmetry).
    - `symmetry`: `NoSymmetry()` (default), `MirrorPairs()` or `SharedMirrorPairs()`.
    - `derivatives`: `"autodiff"` (default: JAX differentiates the network) or `"sympy"`: the
      neuron `α σ(wτ + β)` and its first derivatives in `(α, w, β, τ)` (and those of its
      τ-derivative) are taken by sympy and compiled to JAX once, as the reference's symbolic
      kernels; higher derivatives (the Newton Jacobian) differentiate that compiled code.
      Both give the same solution; on CPU they also cost the same (see
      `benchmarks/derivatives.py`).
    """

    activation: Callable = eqx.field(static=True)
    width: int = eqx.field(static=True)
    symmetry: AbstractSymmetry = eqx.field(static=True, default=NoSymmetry())
    derivatives: str = eqx.field(static=True, default="autodiff")
    coordinatewise: ClassVar[bool] = True

    def __check_init__(self):
        if not callable(self.activation):
            raise TypeError(f"activation must be callable, got {type(self.activation).__name__}")
        if not isinstance(self.width, int) or isinstance(self.width, bool) or self.width < 1:
            raise ValueError(f"width must be a positive integer, got {self.width!r}")
        if not isinstance(self.symmetry, AbstractSymmetry):
            raise TypeError(
                "symmetry must be NoSymmetry(), MirrorPairs() or SharedMirrorPairs(), got "
                f"{self.symmetry!r}"
            )
        if self.derivatives not in ("autodiff", "sympy"):
            raise ValueError(f"derivatives must be 'autodiff' or 'sympy', got {self.derivatives!r}")
        if self.derivatives == "sympy":
            from ..symbolic import sympy_activation  # sympy only when asked for

            sympy_activation(self.activation)  # refuses an activation with no sympy form
        if self.mirrored and self.width % 2:
            raise ValueError(
                f"mirrored neuron pairs need an even width; got width={self.width} with "
                f"{type(self.symmetry).__name__}()"
            )

    @property
    def mirrored(self) -> bool:
        return isinstance(self.symmetry, MirrorPairs | SharedMirrorPairs)

    @property
    def can_advance(self) -> bool:  # type: ignore[override]
        # A continued mirrored pair is no longer a mirrored pair.
        return not self.mirrored

    def num_params(self) -> int:
        s = self.width
        if isinstance(self.symmetry, MirrorPairs):
            return 2 * s
        if isinstance(self.symmetry, SharedMirrorPairs):
            return 3 * s // 2
        return 3 * s

    def split(self, theta: Array) -> tuple[Array, Array, Array]:
        """`(α, w, β)` of all `S` neurons, each of shape `(S, D)` (mirror pairs expanded)."""
        s = self.width
        if not self.mirrored:
            return theta[:s], theta[s : 2 * s], theta[2 * s :]
        k = s // 2
        n_alpha = s if isinstance(self.symmetry, MirrorPairs) else k
        alpha, w, beta = theta[:n_alpha], theta[n_alpha : n_alpha + k], theta[n_alpha + k :]
        if n_alpha == k:
            alpha = jnp.repeat(alpha, 2, axis=0)
        mw, mb = mirror(w, beta)
        return alpha, _interleave(w, mw), _interleave(beta, mb)

    def from_neurons(self, w: Array, b: Array, c: Array) -> Array:
        """The parameter column of one coordinate from per-neuron `(W, b, c)` (each `(S,)`),
        e.g. an OGA fit placed with this basis's symmetry."""
        if not self.mirrored:
            return jnp.concatenate([c, w, b])
        alpha = c if isinstance(self.symmetry, MirrorPairs) else c[0::2]
        return jnp.concatenate([alpha, w[0::2], b[0::2]])

    def num_output_weights(self) -> int:
        """Number of output weights `α` per coordinate (they lead the parameter column)."""
        return self.width // 2 if isinstance(self.symmetry, SharedMirrorPairs) else self.width

    @staticmethod
    def join(alpha: Array, w: Array, beta: Array) -> Array:
        """Parameters of an unmirrored network from `(α, w, β)`."""
        return jnp.concatenate([alpha, w, beta], axis=0)

    def evaluate(self, theta, tau):
        if self.derivatives == "sympy":
            from ..symbolic import symbolic_shallow_evaluate

            return symbolic_shallow_evaluate(self)(theta, tau)
        alpha, w, beta = self.split(theta)
        return jnp.sum(alpha * self.activation(w * tau + beta), axis=0)

    def advance(self, theta, ratio):
        if self.mirrored:
            return super().advance(theta, ratio)
        alpha, w, beta = self.split(theta)
        return self.join(alpha, w * ratio, beta + w)

    def check(self, dtype) -> None:
        check_activation(self.activation, dtype)

    def min_nodes(self) -> int:
        return _network_min_nodes(self.width)

    def __repr__(self):
        extra = "" if not self.mirrored else f", symmetry={type(self.symmetry).__name__}()"
        if self.derivatives != "autodiff":
            extra += f", derivatives={self.derivatives!r}"
        return f"ShallowNetBasis({activation_name(self.activation)}, width={self.width}{extra})"
