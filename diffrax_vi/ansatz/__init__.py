"""Trial trajectories on one step: `q_h(τ; θ)`, `τ ∈ [0, 1]` (networks, polynomials)."""

from .base import AbstractBasis
from .polynomial import LagrangeBasis
from .shallow import ShallowNetBasis
from .symbolic import SymbolicAnsatz, VISEBasis

__all__ = ["AbstractBasis", "LagrangeBasis", "ShallowNetBasis", "SymbolicAnsatz", "VISEBasis"]
