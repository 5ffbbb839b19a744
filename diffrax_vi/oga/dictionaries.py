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
import math

import equinox as eqx
import numpy as np

__all__ = [
    "AbstractDictionary",
    "BiasGrid1d",
    "WeightBiasGrid2d",
    "AngularGrid",
    "Refined",
    "bias_grid",
    "weight_grid",
]


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


def weight_grid(lo_octave: float, hi_octave: float, amount: int, dtype) -> np.ndarray:
    """`amount + 1` magnitudes `2**e`, `e` equally spaced from `lo_octave` to `hi_octave`.

    Exponents and powers are computed in float64 and rounded to `dtype` once (magnitudes out
    of the range of `dtype` saturate to `0` or `inf` predictably).

    **Arguments:**

    - `lo_octave`, `hi_octave`: the end exponents (base 2), `lo_octave <= hi_octave`.
    - `amount`: the number of intervals (a non-negative integer; `0` gives `2**lo_octave`).
    - `dtype`: the floating dtype of the result.
    """
    exponents = np.linspace(np.float64(lo_octave), np.float64(hi_octave), int(amount) + 1)
    with np.errstate(over="ignore"):
        return np.exp2(exponents).astype(np.dtype(dtype))


def _is_int(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _real(value) -> bool:
    return (
        isinstance(value, int | float | np.integer | np.floating)
        and not isinstance(value, bool)
        and math.isfinite(float(value))
    )


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


@functools.lru_cache(maxsize=32)
def _grid_2d_atoms(lo, hi, nb, octaves, weight_amount, signed, dtype_name):
    dtype = np.dtype(dtype_name)
    mags = weight_grid(octaves[0], octaves[1], weight_amount, dtype)
    ws = np.concatenate([-mags, mags]) if signed else mags
    biases = bias_grid(lo, hi, nb, dtype)
    table = np.stack(
        [np.repeat(ws, biases.shape[0]), np.tile(biases, ws.shape[0])], axis=1
    ).astype(dtype)
    table.setflags(write=False)
    return table


class WeightBiasGrid2d(AbstractDictionary):
    """A grid of hidden-weight magnitudes (in octaves) times a uniform bias grid.

    Magnitudes `weight_grid(*octaves, weight_amount)` (ascending); with `signed` the weights
    are the negated magnitudes followed by the magnitudes, e.g. `-1/8, ..., -8, 1/8, ..., 8`
    by default. Biases are `bias_grid(lo, hi, nb)` with `nb = bias_amount` if given, else
    `dict_amount`. Atoms run over the weights in the outer loop and the biases in the inner
    one, so `N = (2 if signed else 1) (weight_amount + 1) (nb + 1)`. With `octaves=(0, 0)`,
    `weight_amount=0`, `signed=True` this is `BiasGrid1d` exactly.

    For activations that are not positively homogeneous (ELU, GELU, tanh) `|w|` is a length
    scale and carries shape information; pair this grid with a scale-invariant selection.

    **Arguments:**

    - `octaves`: `(lo, hi)` base-2 exponents of the magnitudes (default `(-3.0, 3.0)`).
    - `weight_amount`: number of magnitude intervals (default `6`: seven magnitudes).
    - `signed`: include negative weights (default `True`).
    - `bias_amount`: number of bias intervals, or `None` (default) for `dict_amount`.
    """

    octaves: tuple[float, float] = eqx.field(static=True, default=(-3.0, 3.0))
    weight_amount: int = eqx.field(static=True, default=6)
    signed: bool = eqx.field(static=True, default=True)
    bias_amount: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        octaves = self.octaves
        if (
            not isinstance(octaves, tuple)
            or len(octaves) != 2
            or not all(_real(v) for v in octaves)
            or float(octaves[0]) > float(octaves[1])
        ):
            raise ValueError(f"octaves must be a pair (lo, hi) of reals, lo <= hi; got {octaves!r}")
        if not _is_int(self.weight_amount) or self.weight_amount < 0:
            raise ValueError(
                f"weight_amount must be a non-negative integer, got {self.weight_amount!r}"
            )
        if not isinstance(self.signed, bool):
            raise ValueError(f"signed must be a bool, got {self.signed!r}")
        if self.bias_amount is not None and (
            not _is_int(self.bias_amount) or self.bias_amount < 1
        ):
            raise ValueError(
                f"bias_amount must be a positive integer or None, got {self.bias_amount!r}"
            )

    def _nb(self, dict_amount):
        return int(dict_amount if self.bias_amount is None else self.bias_amount)

    def atoms_np(self, bias_interval, dict_amount, dtype):
        lo, hi = bias_interval
        octaves = (float(self.octaves[0]), float(self.octaves[1]))
        return _grid_2d_atoms(
            float(lo),
            float(hi),
            self._nb(dict_amount),
            octaves,
            int(self.weight_amount),
            self.signed,
            np.dtype(dtype).name,
        )

    def size(self, dict_amount: int) -> int:
        return (2 if self.signed else 1) * (int(self.weight_amount) + 1) * (
            self._nb(dict_amount) + 1
        )

    @property
    def label(self) -> str:
        return f"grid2d({int(self.weight_amount) + 1}w)"


@functools.lru_cache(maxsize=32)
def _angular_atoms(radii, n, dtype_name):
    dtype = np.dtype(dtype_name)
    theta = (2 * np.pi * np.arange(n + 1, dtype=np.float64) / (n + 1)).astype(dtype)
    r = np.asarray(radii, np.float64).astype(dtype)
    cos, sin = np.cos(theta).astype(dtype), np.sin(theta).astype(dtype)
    table = np.stack(
        [(r[:, None] * cos[None, :]).reshape(-1), (r[:, None] * sin[None, :]).reshape(-1)],
        axis=1,
    ).astype(dtype)
    table.setflags(write=False)
    return table


class AngularGrid(AbstractDictionary):
    """Atoms `(w, b) = (r cos theta, r sin theta)` spread uniformly over circles.

    With `n = amount` if given, else `dict_amount`, the angles are `theta_i = 2 pi i / (n + 1)`,
    `i = 0..n` (the full circle, endpoint excluded: `sigma(t)` and `sigma(-t)` differ). Atoms
    run over `radii` (in the given order) in the outer loop and the angles in the inner one:
    `N = len(radii) (n + 1)`. Ignores `bias_interval`. Angles are computed in float64 and
    rounded to the working dtype; cosine, sine and the products are rounded to it as well.
    Uniform in the direction of the atom, unlike the bias grid, whose resolution piles up at
    large `|b|` where atoms are nearly constant on `[0, 1]`. Use a scale-invariant selection.

    **Arguments:**

    - `radii`: tuple of positive radii (default `(1.0,)`); for smooth activations the radius
        is the length scale.
    - `amount`: number of angles minus one, or `None` (default) for `dict_amount`.
    """

    radii: tuple[float, ...] = eqx.field(static=True, default=(1.0,))
    amount: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        radii = self.radii
        if (
            not isinstance(radii, tuple)
            or not radii
            or not all(_real(r) and float(r) > 0 for r in radii)
        ):
            raise ValueError(f"radii must be a non-empty tuple of positive reals, got {radii!r}")
        if self.amount is not None and (not _is_int(self.amount) or self.amount < 1):
            raise ValueError(f"amount must be a positive integer or None, got {self.amount!r}")

    def _n(self, dict_amount):
        return int(dict_amount if self.amount is None else self.amount)

    def atoms_np(self, bias_interval, dict_amount, dtype):
        del bias_interval
        radii = tuple(float(r) for r in self.radii)
        return _angular_atoms(radii, self._n(dict_amount), np.dtype(dtype).name)

    def size(self, dict_amount: int) -> int:
        return len(self.radii) * (self._n(dict_amount) + 1)

    @property
    def label(self) -> str:
        return f"angular({len(self.radii)}r)"


class Refined(AbstractDictionary):
    """The atoms of `inner`, with every chosen atom polished off-grid by compass search.

    After the greedy argmax, the winner's `(w, b)` is improved by a derivative-free compass
    search on the normalised score `|<g, r>| / ||g||` (or `/ ||g^perp||` under
    `OrthogonalProjection`): starting from the step `h = (sqrt(eps) + |w| + |b|) / 8`, each
    of `iterations` sweeps tries `(w + h, b)`, `(w - h, b)`, `(w, b + h)`, `(w, b - h)` in this
    order, moving at once on an improvement (later moves start from the moved point); a sweep
    without improvement multiplies `h` by `shrink`, and the search ends once `h <= eps`.
    `4 iterations` extra `O(M)` score evaluations per step. The result reports the grid
    index; coherence blocking uses the grid atom.

    **Arguments:**

    - `inner`: the dictionary whose atoms are searched.
    - `iterations`: number of sweeps (a positive int, default `3`).
    - `shrink`: step factor after a sweep without improvement, in `(0, 1)` (default `0.5`).
    """

    inner: AbstractDictionary = eqx.field(static=True)
    iterations: int = eqx.field(static=True, default=3)
    shrink: float = eqx.field(static=True, default=0.5)

    def __check_init__(self):
        if not isinstance(self.inner, AbstractDictionary) or isinstance(self.inner, Refined):
            raise ValueError(
                f"Refined needs a (non-refined) dictionary to search, got {self.inner!r}"
            )
        if not _is_int(self.iterations) or self.iterations < 1:
            raise ValueError(f"iterations must be a positive integer, got {self.iterations!r}")
        if not _real(self.shrink) or not 0 < float(self.shrink) < 1:
            raise ValueError(f"shrink must lie in (0, 1), got {self.shrink!r}")

    def atoms_np(self, bias_interval, dict_amount, dtype):
        return self.inner.atoms_np(bias_interval, dict_amount, dtype)

    def size(self, dict_amount: int) -> int:
        return self.inner.size(dict_amount)

    @property
    def label(self) -> str:
        return f"refined[{self.inner.label}]"


def bias_pair(bias_interval) -> tuple[float, float]:
    """A bias range as a hashable pair of floats (lists and arrays are accepted)."""
    try:
        lo, hi = (float(v) for v in bias_interval)
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"bias_interval must be a pair of real numbers (lo, hi), got {bias_interval!r}"
        ) from err
    return lo, hi


def dictionary_range(bias_interval, dict_amount) -> tuple[float, float]:
    """The bias range as a pair of floats, after refusing one that is not finite and
    increasing, or a resolution `dict_amount` that is not a positive integer."""
    if (not isinstance(dict_amount, int | np.integer) or isinstance(dict_amount, bool)
            or dict_amount < 1):
        raise ValueError(f"dict_amount must be a positive integer, got {dict_amount!r}")
    lo, hi = bias_pair(bias_interval)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(
            f"bias_interval must be finite and increasing (lo < hi), got {bias_interval!r}"
        )
    return lo, hi

