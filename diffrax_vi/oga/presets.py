"""Named OGA configurations (the reference's presets)."""

from __future__ import annotations

from typing import TypedDict, Unpack

from .base import DEFAULT_BIAS_INTERVAL, DEFAULT_DICT_AMOUNT
from .config import OGA, OGAReference
from .dictionaries import AbstractDictionary, AngularGrid, BiasGrid1d, WeightBiasGrid2d
from .fits import IncrementalQR, WeightedQR
from .selection import NormalizedProjection, OrthogonalProjection, RawProjection

__all__ = [
    "OGAOptions",
    "OGA1d",
    "OGA1dNormalized",
    "OGA1dStable",
    "OGA2d",
    "OGASphere",
    "OGA1dNormalEquations",
]


class OGAOptions(TypedDict, total=False):
    """The keywords every preset passes on to `OGA`: the guard-rail flags `coherence`,
    `norm_guard`, `fill_unused`, and the dictionary's `bias_interval` and `dict_amount`."""

    coherence: bool
    norm_guard: bool
    fill_unused: bool
    bias_interval: tuple[float, float]
    dict_amount: int


def OGA1d(**options: Unpack[OGAOptions]) -> OGA:
    """The default seed: `±1` bias grid, raw projection, pivoted-QR refit (`"grid1d/raw/qr"`).

    Its selected atoms on the reference's test problem are pinned; it is the configuration the
    reference tuned its float64 accuracy guards on.

    **Arguments:**

    - `options`: `OGA`'s guard-rail flags and dictionary range (`OGAOptions`).
    """
    return OGA(
        BiasGrid1d(),
        RawProjection(),
        WeightedQR(),
        **options,
    )


def OGA1dNormalized(**options: Unpack[OGAOptions]) -> OGA:
    """`±1` bias grid with the scale-invariant normalised projection (`"grid1d/normalized/qr"`).

    The reference's default for its interpolating-endpoint ("Autodiff") integrators.

    **Arguments:**

    - `options`: `OGA`'s guard-rail flags and dictionary range (`OGAOptions`).
    """
    return OGA(
        BiasGrid1d(),
        NormalizedProjection(),
        WeightedQR(),
        **options,
    )


def OGA1dStable(**options: Unpack[OGAOptions]) -> OGA:
    """The reduced-precision preset: `±1` bias grid, orthogonal projection with the gain floor
    `sqrt(eps)`, and the incremental-QR refit (`"grid1d/orthogonal/incqr"`).

    **Arguments:**

    - `options`: `OGA`'s guard-rail flags and dictionary range (`OGAOptions`).
    """
    return OGA(
        BiasGrid1d(),
        OrthogonalProjection(),
        IncrementalQR(),
        **options,
    )


def OGA2d(
    dictionary: AbstractDictionary | None = None, **options: Unpack[OGAOptions]
) -> OGA:
    """For smooth activations: weight × bias grid, normalised projection, incremental QR.

    The default dictionary keeps hidden weights `|w| ≤ 1` (magnitudes `1/8, 1/4, 1/2, 1`):
    the reference's grid also has `2, 4, 8`, whose atoms switch within a fraction of the step,
    and seeds built from them left the Newton solve at a residual plateau, where seeds with
    `|w| ≤ 1` converge for tanh and GELU networks. Pass `WeightBiasGrid2d()` for the
    reference's grid.

    **Arguments:**

    - `dictionary`: default `WeightBiasGrid2d(octaves=(-3.0, 0.0), weight_amount=3)`
        (`"grid2d(4w)/normalized/incqr"`).
    - `options`: `OGA`'s guard-rail flags and dictionary range (`OGAOptions`).
    """
    if dictionary is None:
        dictionary = WeightBiasGrid2d(octaves=(-3.0, 0.0), weight_amount=3)
    return OGA(
        dictionary,
        NormalizedProjection(),
        IncrementalQR(),
        **options,
    )


def OGASphere(
    dictionary: AbstractDictionary | None = None, **options: Unpack[OGAOptions]
) -> OGA:
    """Atoms uniform in direction: angular grid, normalised projection, incremental QR.

    **Arguments:**

    - `dictionary`: default `AngularGrid()` (`"angular(1r)/normalized/incqr"`).
    - `options`: `OGA`'s guard-rail flags and dictionary range (`OGAOptions`).
    """
    return OGA(
        AngularGrid() if dictionary is None else dictionary,
        NormalizedProjection(),
        IncrementalQR(),
        **options,
    )


def OGA1dNormalEquations(
    *,
    bias_interval: tuple[float, float] = DEFAULT_BIAS_INTERVAL,
    dict_amount: int = DEFAULT_DICT_AMOUNT,
) -> OGAReference:
    """The reference's original seed as a baseline (`"reference/raw/normaleq+f64"`).

    `±1` bias grid, raw projection of the residual of the `T`-rounded network, and float64
    normal equations without ridge; no guard rails, no blocking of selected atoms, no fill.
    Needs `jax_enable_x64`; for the plain network integrator only (no modulation or
    symmetry). It takes no guard-rail keywords: it has none; `bias_interval` and `dict_amount`
    are those of `OGA`.
    """
    return OGAReference(bias_interval=bias_interval, dict_amount=dict_amount)
