"""Orthogonal greedy fits of shallow networks: the network integrators' initial guess.

The public pieces are the configuration axes (dictionaries, selection rules, fits,
symmetries), the `OGA` record that combines them, the presets, and `oga_fit`.
"""

from ..ansatz.symmetry import AbstractSymmetry as AbstractSymmetry
from ..ansatz.symmetry import MirrorPairs as MirrorPairs
from ..ansatz.symmetry import NoSymmetry as NoSymmetry
from ..ansatz.symmetry import SharedMirrorPairs as SharedMirrorPairs
from ..ansatz.symmetry import mirror as mirror
from .base import AbstractOGA as AbstractOGA
from .config import OGA as OGA
from .config import OGAReference as OGAReference
from .dictionaries import AbstractDictionary as AbstractDictionary
from .dictionaries import AngularGrid as AngularGrid
from .dictionaries import BiasGrid1d as BiasGrid1d
from .dictionaries import Refined as Refined
from .dictionaries import WeightBiasGrid2d as WeightBiasGrid2d
from .dictionaries import bias_grid as bias_grid
from .dictionaries import weight_grid as weight_grid
from .fits import AbstractFit as AbstractFit
from .fits import IncrementalQR as IncrementalQR
from .fits import NormalEquationsFit as NormalEquationsFit
from .fits import PivotedQR as PivotedQR
from .fits import TruncatedSVD as TruncatedSVD
from .fits import WeightedQR as WeightedQR
from .fits import guarded_solve as guarded_solve
from .fits import ridged_lstsq as ridged_lstsq
from .greedy import oga_fit as oga_fit
from .network_fit import fit_network as fit_network
from .presets import OGA1d as OGA1d
from .presets import OGA1dNormalEquations as OGA1dNormalEquations
from .presets import OGA1dNormalized as OGA1dNormalized
from .presets import OGA1dStable as OGA1dStable
from .presets import OGA2d as OGA2d
from .presets import OGAOptions as OGAOptions
from .presets import OGASphere as OGASphere
from .qr import QRState as QRState
from .qr import jacobi_svd as jacobi_svd
from .qr import lu_solve as lu_solve
from .qr import pivoted_lstsq as pivoted_lstsq
from .qr import qr_append as qr_append
from .qr import qr_init as qr_init
from .qr import upper_solve as upper_solve
from .result import OGAResult as OGAResult
from .selection import AbstractSelection as AbstractSelection
from .selection import NormalizedProjection as NormalizedProjection
from .selection import OrthogonalProjection as OrthogonalProjection
from .selection import RawProjection as RawProjection
