"""Named OGA configurations (the reference's presets)."""

from __future__ import annotations

from .config import OGA, OGAReference
from .dictionaries import AbstractDictionary, AngularGrid, BiasGrid1d, WeightBiasGrid2d
from .fits import IncrementalQR, WeightedQR
from .selection import NormalizedProjection, OrthogonalProjection, RawProjection

__all__ = [
    "OGA1d",
    "OGA1dNormalized",
    "OGA1dStable",
    "OGA2d",
    "OGASphere",
    "OGA1dNormalEquations",
]


def OGA1d(*, coherence: bool = True, norm_guard: bool = True, fill_unused: bool = True) -> OGA:
    """The default seed: `±1` bias grid, raw projection, pivoted-QR refit (`"grid1d/raw/qr"`).

    Its selected atoms on the reference's test problem are pinned; it is the configuration the
    reference tuned its float64 accuracy guards on.

    **Arguments:**

    - `coherence`, `norm_guard`, `fill_unused`: the guard-rail flags of `OGA`.
    """
    return OGA(
        BiasGrid1d(),
        RawProjection(),
        WeightedQR(),
        coherence=coherence,
        norm_guard=norm_guard,
        fill_unused=fill_unused,
    )


def OGA1dNormalized(
    *, coherence: bool = True, norm_guard: bool = True, fill_unused: bool = True
) -> OGA:
    """`±1` bias grid with the scale-invariant normalised projection (`"grid1d/normalized/qr"`).

    The reference's default for its interpolating-endpoint ("Autodiff") integrators.

    **Arguments:**

    - `coherence`, `norm_guard`, `fill_unused`: the guard-rail flags of `OGA`.
    """
    return OGA(
        BiasGrid1d(),
        NormalizedProjection(),
        WeightedQR(),
        coherence=coherence,
        norm_guard=norm_guard,
        fill_unused=fill_unused,
    )


def OGA1dStable(
    *, coherence: bool = True, norm_guard: bool = True, fill_unused: bool = True
) -> OGA:
    """The reduced-precision preset: `±1` bias grid, orthogonal projection with the gain floor
    `sqrt(eps)`, and the incremental-QR refit (`"grid1d/orthogonal/incqr"`).

    **Arguments:**

    - `coherence`, `norm_guard`, `fill_unused`: the guard-rail flags of `OGA`.
    """
    return OGA(
        BiasGrid1d(),
        OrthogonalProjection(),
        IncrementalQR(),
        coherence=coherence,
        norm_guard=norm_guard,
        fill_unused=fill_unused,
    )


def OGA2d(
    dictionary: AbstractDictionary | None = None,
    *,
    coherence: bool = True,
    norm_guard: bool = True,
    fill_unused: bool = True,
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
    - `coherence`, `norm_guard`, `fill_unused`: the guard-rail flags of `OGA`.
    """
    if dictionary is None:
        dictionary = WeightBiasGrid2d(octaves=(-3.0, 0.0), weight_amount=3)
    return OGA(
        dictionary,
        NormalizedProjection(),
        IncrementalQR(),
        coherence=coherence,
        norm_guard=norm_guard,
        fill_unused=fill_unused,
    )


def OGASphere(
    dictionary: AbstractDictionary | None = None,
    *,
    coherence: bool = True,
    norm_guard: bool = True,
    fill_unused: bool = True,
) -> OGA:
    """Atoms uniform in direction: angular grid, normalised projection, incremental QR.

    **Arguments:**

    - `dictionary`: default `AngularGrid()` (`"angular(1r)/normalized/incqr"`).
    - `coherence`, `norm_guard`, `fill_unused`: the guard-rail flags of `OGA`.
    """
    return OGA(
        AngularGrid() if dictionary is None else dictionary,
        NormalizedProjection(),
        IncrementalQR(),
        coherence=coherence,
        norm_guard=norm_guard,
        fill_unused=fill_unused,
    )


def OGA1dNormalEquations() -> OGAReference:
    """The reference's original seed as a baseline (`"reference/raw/normaleq+f64"`).

    `±1` bias grid, raw projection of the residual of the `T`-rounded network, and float64
    normal equations without ridge; no guard rails, no blocking of selected atoms, no fill.
    Needs `jax_enable_x64`; for the plain network integrator only (no modulation or
    symmetry). It takes no guard-rail keywords: it has none.
    """
    return OGAReference()
