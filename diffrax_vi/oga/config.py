"""The OGA seeds: one point in dictionary × selection × fit with its guard rails and its
dictionary's range and resolution (`OGA`), and the reference's verbatim seed
(`OGAReference`). Both are parameter seeds of a `ShallowNetBasis`."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx

from .base import AbstractOGA
from .dictionaries import AbstractDictionary, BiasGrid1d
from .fits import AbstractFit, WeightedQR
from .selection import AbstractSelection, RawProjection

__all__ = ["OGA", "OGAReference"]


class OGA(AbstractOGA):
    """The orthogonal greedy fit that seeds a shallow network: a parameter seed
    (`initial_guess`) and the configuration `oga_fit` runs.

    A static, hashable value (all fields are static), so it can sit in a static field of a
    solver or be passed to `oga_fit` under `jax.jit` without becoming a traced argument. Its
    three axes are independent; the three flags switch the guard rails.

    **Arguments:**

    - `dictionary`: the candidate atoms `(w, b)`; default `BiasGrid1d()`.
    - `selection`: how atoms are scored against the residual; default `RawProjection()`.
    - `fit`: how all output weights are refitted after each accepted atom; default
        `WeightedQR()`.
    - `coherence`: after accepting an atom, also block every atom whose cosine with it exceeds
        `1 - sqrt(eps)` in magnitude (near duplicates after rounding). The accepted atom itself
        is blocked regardless. Default `True`.
    - `norm_guard`: treat atoms whose norm is at most `sqrt(eps)` times the largest finite norm
        as unusable. When off, only atoms with zero or non-finite norm are unusable (non-finite
        norms are always excluded). Default `True`.
    - `fill_unused`: when the loop places fewer neurons than requested, give the remaining ones
        distinct usable atoms with zero output weight instead of leaving them at `(0, 0)`.
        Default `True`.
    - `bias_interval`: the range `(lo, hi)` of the grid dictionaries' biases. Default
        `(-π, π)`.
    - `dict_amount`: the dictionary's resolution (the number of bias intervals of
        `BiasGrid1d`). Default 4000.
    """

    dictionary: AbstractDictionary = eqx.field(static=True, default_factory=BiasGrid1d)
    selection: AbstractSelection = eqx.field(static=True, default_factory=RawProjection)
    fit: AbstractFit = eqx.field(static=True, default_factory=WeightedQR)
    coherence: bool = eqx.field(static=True, default=True, kw_only=True)
    norm_guard: bool = eqx.field(static=True, default=True, kw_only=True)
    fill_unused: bool = eqx.field(static=True, default=True, kw_only=True)

    reference: ClassVar[bool] = False

    def __check_init__(self):
        for name, base in (
            ("dictionary", AbstractDictionary),
            ("selection", AbstractSelection),
            ("fit", AbstractFit),
        ):
            value = getattr(self, name)
            if not isinstance(value, base):
                raise ValueError(
                    f"OGA {name} must be an instance of {base.__name__}, got {value!r}"
                )
        for name in ("coherence", "norm_guard", "fill_unused"):
            value = getattr(self, name)
            if not isinstance(value, bool):
                raise ValueError(f"OGA {name} must be a bool, got {value!r}")

    @property
    def label(self) -> str:
        """`"<dictionary>/<selection>/<fit>"`, e.g. `"grid1d/raw/qr"` for `OGA1d()`."""
        return f"{self.dictionary.label}/{self.selection.label}/{self.fit.label}"


class OGAReference(AbstractOGA):
    """The reference's original seed, kept verbatim as a baseline (see `OGA1dNormalEquations`).

    Not a point of the dictionary × selection × fit space: it has none of the guard rails and
    deliberately computes in float64 (needs `jax_enable_x64`). `oga_fit` dispatches on it.
    Only for `NoSymmetry` and no modulation (the plain network integrator). `bias_interval`
    and `dict_amount` are those of `OGA`.
    """


    reference: ClassVar[bool] = True


    @property
    def label(self) -> str:
        """`"reference/raw/normaleq+f64"`."""
        return "reference/raw/normaleq+f64"
