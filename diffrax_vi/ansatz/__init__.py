"""Trial trajectories on one step: `q_h(τ; θ)`, `τ ∈ [0, 1]` (networks, polynomials)."""

from .base import AbstractBasis
from .polynomial import LagrangeBasis
from .shallow import ShallowNetBasis

__all__ = ["AbstractBasis", "LagrangeBasis", "ShallowNetBasis"]
