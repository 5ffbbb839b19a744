"""Named OGA configurations (the reference's presets)."""

from __future__ import annotations

from .config import OGA
from .dictionaries import BiasGrid1d
from .fits import WeightedQR
from .selection import NormalizedProjection, RawProjection

__all__ = ["OGA1d", "OGA1dNormalized"]


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
