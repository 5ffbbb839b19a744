"""Trial trajectories on one step: `q_h(τ; θ)`, `τ ∈ [0, 1]` (networks, polynomials).

Ansätze written with sympy (`VISEBasis`, `SymbolicAnsatz`) live in `diffrax_vi.symbolic.ansatz`.
"""

from .base import AbstractBasis
from .dense import DenseNetBasis
from .polynomial import LagrangeBasis
from .shallow import ShallowNetBasis

__all__ = [
    "AbstractBasis",
    "DenseNetBasis",
    "LagrangeBasis",
    "ShallowNetBasis",
]
