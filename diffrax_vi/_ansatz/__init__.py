"""Trial trajectories on one step: `q_h(τ; θ)`, `τ ∈ [0, 1]` (networks, polynomials).

Ansätze written with sympy (`VISEBasis`, `SymbolicAnsatz`) live in `diffrax_vi.symbolic.ansatz`.
"""

from .base import AbstractBasis as AbstractBasis
from .dense import DenseNetBasis as DenseNetBasis
from .polynomial import LagrangeBasis as LagrangeBasis
from .shallow import ShallowNetBasis as ShallowNetBasis
