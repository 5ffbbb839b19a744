"""Orthogonal greedy fits of shallow networks: the network integrators' initial guess.

An `OGA` record combines four independent choices (a dictionary of candidate neurons, a
selection rule, a least-squares fit, a symmetry of the neurons); the presets name common
combinations, and `oga_fit` runs one fit on sampled data.
"""

from .base import AbstractOGA as AbstractOGA
from .config import OGA as OGA
from .dictionaries import AngularGrid as AngularGrid
from .dictionaries import BiasGrid1d as BiasGrid1d
from .dictionaries import Refined as Refined
from .dictionaries import WeightBiasGrid2d as WeightBiasGrid2d
from .fits import IncrementalQR as IncrementalQR
from .fits import NormalEquationsFit as NormalEquationsFit
from .fits import PivotedQR as PivotedQR
from .fits import TruncatedSVD as TruncatedSVD
from .fits import WeightedQR as WeightedQR
from .greedy import oga_fit as oga_fit
from .network_fit import fit_network as fit_network
from .presets import OGA1d as OGA1d
from .presets import OGA1dNormalEquations as OGA1dNormalEquations
from .presets import OGA1dNormalized as OGA1dNormalized
from .presets import OGA1dStable as OGA1dStable
from .presets import OGA2d as OGA2d
from .presets import OGAOptions as OGAOptions
from .presets import OGASphere as OGASphere
from .result import OGAResult as OGAResult
from .selection import NormalizedProjection as NormalizedProjection
from .selection import OrthogonalProjection as OrthogonalProjection
from .selection import RawProjection as RawProjection

__all__ = [
    "OGA",
    "AbstractOGA",
    "AngularGrid",
    "BiasGrid1d",
    "IncrementalQR",
    "NormalEquationsFit",
    "NormalizedProjection",
    "OGA1d",
    "OGA1dNormalEquations",
    "OGA1dNormalized",
    "OGA1dStable",
    "OGA2d",
    "OGAOptions",
    "OGAResult",
    "OGASphere",
    "OrthogonalProjection",
    "PivotedQR",
    "RawProjection",
    "Refined",
    "TruncatedSVD",
    "WeightBiasGrid2d",
    "WeightedQR",
    "fit_network",
    "oga_fit",
]


def __dir__():
    return sorted(__all__)
