"""How one selected atom becomes neurons and design columns.

A symmetry fixes the maps used by the greedy loop: atom → scoring row (what the selection
rule sees), atom → fit columns (what the refit sees), atoms → neurons (which `(w, b)` the
network gets) and fitted coefficients → output weights. Besides the plain
one-neuron-per-atom map there are mirrored pairs: `(w, b)` together with
`mirror(w, b) = (-w, w + b)`, whose neuron `sigma(-w t + w + b) = sigma(w (1 - t) + b)` is the
first one reflected about `t = 1/2` (for the time-reversible integrators).
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["AbstractSymmetry", "NoSymmetry", "MirrorPairs", "SharedMirrorPairs", "mirror"]


def mirror(w: Array, b: Array) -> tuple[Array, Array]:
    """The mirror map `(w, b) -> (-w, w + b)` (reflection of the neuron about `t = 1/2`).

    Computed in the dtype of the inputs; `w + b` is rounded once, and the mirrored neuron is
    always evaluated from these rounded parameters, so the network and the fit agree exactly.
    """
    return -w, w + b


class AbstractSymmetry(eqx.Module):
    """Base class of the atom → neuron maps.

    Subclasses set the class attributes `neurons_per_atom` and `columns_per_atom` and
    implement the abstract methods below. All arrays are in the working dtype and "scaled" means
    multiplied, row-wise, by `colscale` (square-root weights, modulation and the dictionary's
    power-of-two factor).
    """

    neurons_per_atom: eqx.AbstractClassVar[int]
    columns_per_atom: eqx.AbstractClassVar[int]

    @abc.abstractmethod
    def scoring_rows(
        self,
        activation: Callable,
        w: Array,
        b: Array,
        nodes: Array,
        colscale: Array,
    ) -> Array:
        """The scaled vectors the selection rule scores, one row per atom."""

    @abc.abstractmethod
    def fit_columns(
        self,
        activation: Callable,
        w: Array,
        b: Array,
        nodes: Array,
        colscale: Array,
        row: Array,
    ) -> Array:
        """The `columns_per_atom` scaled design columns of one atom; `row` is its scoring row."""

    @abc.abstractmethod
    def neurons(self, w: Array, b: Array) -> tuple[Array, Array]:
        """Per-neuron `(W, b)` from the per-atom-slot `(w, b)` (`G` slots, `S` neurons)."""

    @abc.abstractmethod
    def coefficients(self, x: Array, width: int) -> Array:
        """Per-neuron output weights from the `K` fitted design coefficients."""

    def check_width(self, width: int) -> None:
        """Raise `ValueError` unless `width` is a multiple of `neurons_per_atom`."""
        if width % self.neurons_per_atom:
            raise ValueError(
                f"{type(self).__name__} places {self.neurons_per_atom} neurons per atom, so the "
                f"width must be a multiple of {self.neurons_per_atom}; got {width}"
            )


class NoSymmetry(AbstractSymmetry):
    """One neuron `sigma(w t + b)` and one design column per atom, independent weights."""

    neurons_per_atom: ClassVar[int] = 1
    columns_per_atom: ClassVar[int] = 1

    def scoring_rows(self, activation, w, b, nodes, colscale):
        return activation(w[:, None] * nodes[None, :] + b[:, None]) * colscale[None, :]

    def fit_columns(self, activation, w, b, nodes, colscale, row):
        del activation, w, b, nodes, colscale
        return row[:, None]

    def neurons(self, w, b):
        return w, b

    def coefficients(self, x, width):
        if x.shape[0] >= width:
            return x[:width]
        return jnp.concatenate([x, jnp.zeros((width - x.shape[0],), x.dtype)])


def _interleave(a: Array, b: Array) -> Array:
    return jnp.stack([a, b], axis=1).reshape(-1)


class MirrorPairs(AbstractSymmetry):
    """Two neurons per atom, `(w, b)` and `mirror(w, b)`, with independent output weights.

    The selection scores only the primary neuron `sigma(w t + b)`; the mirrored neuron is
    added as a second design column when the atom is accepted (the atom is refused if either
    column adds no new direction, and its gain is the smaller of the two). Neuron `2s` is the
    atom of step `s`, neuron `2s + 1` its mirror (0-based). The width must be even.
    """

    neurons_per_atom: ClassVar[int] = 2
    columns_per_atom: ClassVar[int] = 2

    def scoring_rows(self, activation, w, b, nodes, colscale):
        return activation(w[:, None] * nodes[None, :] + b[:, None]) * colscale[None, :]

    def fit_columns(self, activation, w, b, nodes, colscale, row):
        mw, mb = mirror(w, b)
        return jnp.stack([row, activation(mw * nodes + mb) * colscale], axis=1)

    def neurons(self, w, b):
        mw, mb = mirror(w, b)
        return _interleave(w, mw), _interleave(b, mb)

    def coefficients(self, x, width):
        return x[:width]


class SharedMirrorPairs(AbstractSymmetry):
    """Two neurons per atom, `(w, b)` and `mirror(w, b)`, sharing one output weight.

    Selection and fit both see the summed pair `sigma(w t + b) + sigma(w (1 - t) + b)` (one
    design column per atom), and the fitted coefficient is copied to both neurons, so the
    network is symmetric under `t -> 1 - t` pairwise. The width must be even.
    """

    neurons_per_atom: ClassVar[int] = 2
    columns_per_atom: ClassVar[int] = 1

    def scoring_rows(self, activation, w, b, nodes, colscale):
        mw, mb = mirror(w, b)
        primary = activation(w[:, None] * nodes[None, :] + b[:, None])
        mirrored = activation(mw[:, None] * nodes[None, :] + mb[:, None])
        return (primary + mirrored) * colscale[None, :]

    def fit_columns(self, activation, w, b, nodes, colscale, row):
        del activation, w, b, nodes, colscale
        return row[:, None]

    def neurons(self, w, b):
        mw, mb = mirror(w, b)
        return _interleave(w, mw), _interleave(b, mb)

    def coefficients(self, x, width):
        return jnp.repeat(x, 2)[:width]
