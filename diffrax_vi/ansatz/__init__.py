"""Trial trajectories on one step: `q_h(τ; θ)`, `τ ∈ [0, 1]` (networks, polynomials)."""

from .base import AbstractBasis
from .dense import DenseNetBasis
from .polynomial import LagrangeBasis
from .shallow import ShallowNetBasis

__all__ = [
    "AbstractBasis",
    "DenseNetBasis",
    "LagrangeBasis",
    "ShallowNetBasis",
    "SymbolicAnsatz",
    "VISEBasis",
]


def __getattr__(name):
    # The symbolic ansatz needs sympy (slow to import): load it on first use.
    if name in ("SymbolicAnsatz", "VISEBasis"):
        from . import symbolic

        return getattr(symbolic, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
