"""How one selected atom becomes neurons and design columns.

A symmetry fixes the maps used by the greedy loop: atom → scoring row (what the selection
rule sees), atom → fit columns (what the refit sees), atoms → neurons (which `(w, b)` the
network gets) and fitted coefficients → output weights. Only the plain one-neuron-per-atom
map exists so far; mirrored pairs (`(w, b)` together with `(-w, w + b)`, i.e. the neuron
reflected about `t = 1/2`) fit the same interface with two neurons per atom.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["AbstractSymmetry", "NoSymmetry"]


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
