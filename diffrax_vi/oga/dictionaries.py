"""Candidate sets of hidden-neuron parameters `(w, b)` for the greedy fit.

A dictionary turns the per-method inputs `bias_interval` and `dict_amount` into a fixed table
of atoms, one row `(w, b)` per candidate neuron `sigma(w t + b)`. The table is built once, on
the host, at trace time; its size is static. Row order matters: the greedy argmax breaks ties
in favour of the lowest index, so two dictionaries with the same atoms in another order are
different configurations.
"""

from __future__ import annotations

import abc
import functools

import equinox as eqx
import numpy as np

__all__ = ["AbstractDictionary", "BiasGrid1d", "bias_grid"]


def bias_grid(lo: float, hi: float, amount: int, dtype) -> np.ndarray:
    """`amount + 1` equally spaced values from `lo` to `hi` (both included), as `dtype`.

    The values are generated in float64 from integer indices and rounded to `dtype` once,
    so a grid finer than the spacing of `dtype` (e.g. 70000 intervals in float16) still has
    finite, ordered entries; neighbouring values may coincide after the rounding.

    **Arguments:**

    - `lo`, `hi`: the end points, `lo < hi`.
    - `amount`: the number of intervals (a positive integer).
    - `dtype`: the floating dtype of the result.
    """
    return np.linspace(np.float64(lo), np.float64(hi), int(amount) + 1).astype(np.dtype(dtype))


class AbstractDictionary(eqx.Module):
    """Base class of OGA dictionaries: a static, hashable recipe for a table of atoms.

    Subclasses implement `atoms_np`, returning an `(N, 2)` NumPy array in the working dtype
    whose columns are the hidden weight `w` and the bias `b`, and `size`, returning `N`
    without building the table. They may also override `label`.
    """

    @abc.abstractmethod
    def atoms_np(self, bias_interval: tuple[float, float], dict_amount: int, dtype) -> np.ndarray:
        """The `(N, 2)` table of atoms `(w, b)` in `dtype`, in selection (tie-break) order."""

    @abc.abstractmethod
    def size(self, dict_amount: int) -> int:
        """The number of atoms `N` the table has for this `dict_amount`."""

    @property
    def label(self) -> str:
        """A short name used in configuration labels."""
        return type(self).__name__


@functools.lru_cache(maxsize=32)
def _bias_grid_1d_atoms(lo: float, hi: float, amount: int, dtype_name: str) -> np.ndarray:
    dtype = np.dtype(dtype_name)
    biases = bias_grid(lo, hi, amount, dtype)
    ones = np.ones_like(biases)
    table = np.concatenate(
        [np.stack([-ones, biases], axis=1), np.stack([ones, biases], axis=1)], axis=0
    )
    table.setflags(write=False)
    return table


class BiasGrid1d(AbstractDictionary):
    """Hidden weight `±1` combined with a uniform grid of biases.

    With `B` = `bias_grid(lo, hi, dict_amount)` (so `dict_amount + 1` biases), the atoms are
    first `(-1, b)` for every `b` in `B` in increasing order, then `(+1, b)` likewise:
    `N = 2 (dict_amount + 1)`. For the positively homogeneous ReLU powers only the sign of `w`
    carries shape information (a magnitude rescales the atom and its bias), so this grid is
    complete for them up to the bias resolution; smooth activations would also need other
    magnitudes.
    """

    def atoms_np(self, bias_interval, dict_amount, dtype):
        lo, hi = bias_interval
        return _bias_grid_1d_atoms(float(lo), float(hi), int(dict_amount), np.dtype(dtype).name)

    def size(self, dict_amount: int) -> int:
        return 2 * (int(dict_amount) + 1)

    @property
    def label(self) -> str:
        return "grid1d"
