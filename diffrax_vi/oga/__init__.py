"""Orthogonal greedy fits of shallow networks: the network integrators' initial guess.

The public pieces are the configuration axes (dictionaries, selection rules, fits,
symmetries), the `OGA` record that combines them, the presets, and `oga_fit`.
"""

from .config import OGA as OGA
from .dictionaries import AbstractDictionary as AbstractDictionary
from .dictionaries import BiasGrid1d as BiasGrid1d
from .dictionaries import bias_grid as bias_grid
from .fits import AbstractFit as AbstractFit
from .fits import WeightedQR as WeightedQR
from .fits import guarded_solve as guarded_solve
from .fits import ridged_lstsq as ridged_lstsq
from .greedy import OGAResult as OGAResult
from .greedy import oga_fit as oga_fit
from .presets import OGA1d as OGA1d
from .presets import OGA1dNormalized as OGA1dNormalized
from .qr import QRState as QRState
from .qr import pivoted_lstsq as pivoted_lstsq
from .qr import qr_append as qr_append
from .qr import qr_init as qr_init
from .selection import AbstractSelection as AbstractSelection
from .selection import NormalizedProjection as NormalizedProjection
from .selection import RawProjection as RawProjection
from .symmetry import AbstractSymmetry as AbstractSymmetry
from .symmetry import NoSymmetry as NoSymmetry
