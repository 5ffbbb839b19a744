"""Where a projected step's hidden layer comes from: a fixed layer, or a seed fit's.

The rules are options of `VariableProjection` (its `hidden` field): `UniformLayer` (the
default) fixes one layer for every step, so that no step fits a seed; `FirstSeedLayer` keeps
the first step's seed fit; `SeedLayer` takes each step's own.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._activations import ReLUk, gelu, gelu_exact, sigmoid, tanh
from ._ansatz.shallow import ShallowNetBasis

__all__ = ["AbstractHiddenLayer", "FirstSeedLayer", "SeedLayer", "UniformLayer"]


class AbstractHiddenLayer(eqx.Module):
    """Where a projected step's hidden layer `(w, β)` comes from."""

    def fixed_parameters(self, basis, dim: int, dtype) -> Array | None:
        """Parameters whose hidden layer is the same on every step, known when the step is
        traced (for a linear ansatz, its zero coefficients); `None` where the layer comes
        from a seed fit."""
        del basis, dim, dtype
        return None


class SeedLayer(AbstractHiddenLayer):
    """The hidden layer of each step's own seed (the OGA fit of the trajectory seed, or
    whichever `initial_guess` the solver has): a fit on every step."""


class FirstSeedLayer(AbstractHiddenLayer):
    """The hidden layer of the first step's seed, kept for every later step; each later step
    starts from the previous step's curve continued, so only the first step fits a seed."""


class UniformLayer(AbstractHiddenLayer):
    """A fixed hidden layer in the step's local time: neuron `i` of `S` has weight
    `±scale` (alternating signs) and is centred (`w τ + β = 0`) at `τ_i`, the centres spread
    uniformly over `centres` (for `relu_k`, the neurons centred outside the step face it). The
    same layer on every step and in every coordinate, so the step needs no seed fit and its
    result is a continuous function of the state. Designed for the activations of `suits`:
    with equal `|w|`, periodic units span two functions only, and `elu` or `relu_k(1)` little
    more than the linear ones.

    **Arguments:**

    - `scale`: `|w|` of every neuron. Default 0.5.
    - `centres`: the interval `(a, b)` the centres spread over, in units of the step.
      Default `(-4.0, 5.0)`: centres well outside the step make the features smooth on it,
      so that their span holds the low-degree polynomials a smooth motion needs.
    """

    scale: float = eqx.field(static=True, default=0.5)
    centres: tuple[float, float] = eqx.field(static=True, default=(-4.0, 5.0))

    def __check_init__(self):
        if not (isinstance(self.scale, int | float) and not isinstance(self.scale, bool)
                and self.scale > 0 and math.isfinite(self.scale)):
            raise ValueError(f"scale must be a positive number, got {self.scale!r}")
        pair = isinstance(self.centres, tuple) and len(self.centres) == 2 and all(
            isinstance(c, int | float) and not isinstance(c, bool) for c in self.centres
        )
        if not (pair and all(map(math.isfinite, self.centres))
                and self.centres[0] < self.centres[1]):
            raise ValueError(f"centres must be a finite increasing pair, got {self.centres!r}")

    @staticmethod
    def suits(activation) -> bool:
        """Whether the layer's features span a rich enough space on a step for `activation`
        (`tanh`, `sigmoid`, `gelu`, `gelu_exact`, `relu_k` with `k >= 2`; JAX's own names
        for them are recognised by `ShallowNetBasis`, not here)."""
        if isinstance(activation, ReLUk):
            return activation.k >= 2
        return activation in (tanh, sigmoid, gelu, gelu_exact)

    def fixed_parameters(self, basis, dim: int, dtype) -> Array:
        if isinstance(basis, ShallowNetBasis):
            return self.parameters(basis, dim, dtype)
        # a linear ansatz: assembled in NumPy, as `parameters` is
        return jnp.asarray(np.zeros((basis.num_params(), dim)), dtype)

    def parameters(self, basis: ShallowNetBasis, dim: int, dtype) -> Array:
        """The network parameters `(α = 0, w, β)`, each `(S, D)`."""
        width = basis.width
        lo, hi = self.centres
        step = (hi - lo) / max(width - 1, 1)
        centres = np.array([lo + step * i for i in range(width)])
        signs = np.where(np.arange(width) % 2 == 0, 1.0, -1.0)
        if isinstance(basis.activation, ReLUk):
            # a rectified unit is zero on one side of its centre: the neurons centred outside
            # the step face it, or half of them would vanish there
            signs = np.where(centres <= 0, 1.0, np.where(centres >= 1, -1.0, signs))
        w = self.scale * signs
        columns = np.stack([w, -w * centres])  # (2, S)
        w_beta = np.repeat(columns[:, :, None], dim, axis=2)
        # assembled in NumPy: known when the step is traced, it compiles nothing
        return jnp.asarray(np.concatenate([np.zeros((width, dim)), w_beta[0], w_beta[1]]), dtype)
