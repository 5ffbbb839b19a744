"""Trial trajectories on one step: the network (or polynomial) `q_h(τ; θ)`, `τ ∈ [0, 1]`."""

from .base import AbstractBasis
from .shallow import ShallowNetBasis

__all__ = ["AbstractBasis", "ShallowNetBasis"]
