"""Explicit symplectic solvers for separable Lagrangians (kick-drift splittings, symmetric
compositions of Störmer-Verlet, RKN splittings) and RATTLE for holonomic constraints.

Private: the public names are exported from `diffrax_vi`.
"""

from ._coefficients import composition_gammas as composition_gammas
from ._solvers import AbstractSplittingSolver as AbstractSplittingSolver
from ._solvers import BlanesMoan as BlanesMoan
from ._solvers import Composition as Composition
from ._solvers import SplittingState as SplittingState
from ._solvers import StormerVerlet as StormerVerlet
