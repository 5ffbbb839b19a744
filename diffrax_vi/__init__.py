"""diffrax_vi: neural-network variational integrators for Lagrangian mechanics, as diffrax solvers.

float64 needs `jax.config.update("jax_enable_x64", True)`; the library never flips it.
"""

import types as _types

from . import oga as oga
from . import problems as problems
from .activations import elu as elu
from .activations import gelu as gelu
from .activations import gelu_exact as gelu_exact
from .activations import relu_k as relu_k
from .activations import sigmoid as sigmoid
from .activations import sin as sin
from .activations import tanh as tanh
from .ansatz import AbstractBasis as AbstractBasis
from .ansatz import DenseNetBasis as DenseNetBasis
from .ansatz import LagrangeBasis as LagrangeBasis
from .ansatz import ShallowNetBasis as ShallowNetBasis
from .ensemble import ensemble as ensemble
from .ensemble import ensemble_gather as ensemble_gather
from .ensemble import ensemble_mesh as ensemble_mesh
from .fallback import AllParameterFallbackWarning as AllParameterFallbackWarning
from .fixed_point import FixedPointIteration as FixedPointIteration
from .formulation import AbstractFormulation as AbstractFormulation
from .formulation import FreeEndpoints as FreeEndpoints
from .formulation import InterpolatingEndpoints as InterpolatingEndpoints
from .interpolation import NetworkInterpolation as NetworkInterpolation
from .methods import CGVI as CGVI
from .methods import VISE as VISE
from .methods import DenseNet as DenseNet
from .methods import ShallowNet as ShallowNet
from .methods import ShallowNetAutodiff as ShallowNetAutodiff
from .methods import ShallowNetAutodiffReversible as ShallowNetAutodiffReversible
from .methods import ShallowNetReversible as ShallowNetReversible
from .nonlinear import LevenbergMarquardt as LevenbergMarquardt
from .nonlinear import RegularisedNewton as RegularisedNewton
from .oga import OGA as OGA
from .oga import AngularGrid as AngularGrid
from .oga import BiasGrid1d as BiasGrid1d
from .oga import IncrementalQR as IncrementalQR
from .oga import MirrorPairs as MirrorPairs
from .oga import NormalEquationsFit as NormalEquationsFit
from .oga import NormalizedProjection as NormalizedProjection
from .oga import NoSymmetry as NoSymmetry
from .oga import OGA1d as OGA1d
from .oga import OGA1dNormalEquations as OGA1dNormalEquations
from .oga import OGA1dNormalized as OGA1dNormalized
from .oga import OGA1dStable as OGA1dStable
from .oga import OGA2d as OGA2d
from .oga import OGASphere as OGASphere
from .oga import OrthogonalProjection as OrthogonalProjection
from .oga import PivotedQR as PivotedQR
from .oga import RawProjection as RawProjection
from .oga import Refined as Refined
from .oga import SharedMirrorPairs as SharedMirrorPairs
from .oga import TruncatedSVD as TruncatedSVD
from .oga import WeightBiasGrid2d as WeightBiasGrid2d
from .oga import WeightedQR as WeightedQR
from .oga import oga_fit as oga_fit
from .projection import FirstSeedLayer as FirstSeedLayer
from .projection import RoundoffNewton as RoundoffNewton
from .projection import SeedLayer as SeedLayer
from .projection import UniformLayer as UniformLayer
from .projection import VariableProjection as VariableProjection
from .quadrature import GaussLegendre as GaussLegendre
from .quadrature import Simpson as Simpson
from .results import StepReport as StepReport
from .results import describe_failure as describe_failure
from .results import failure_kind as failure_kind
from .seeding import LSGD as LSGD
from .seeding import AbstractInitialTrajectory as AbstractInitialTrajectory
from .seeding import AbstractParameterSeed as AbstractParameterSeed
from .seeding import HermiteExtrapolation as HermiteExtrapolation
from .seeding import InitialWeights as InitialWeights
from .seeding import IntegratorExtrapolation as IntegratorExtrapolation
from .seeding import LeastSquaresFit as LeastSquaresFit
from .seeding import NoExtrapolation as NoExtrapolation
from .seeding import PreviousStep as PreviousStep
from .seeding import SeedPolicy as SeedPolicy
from .seeding import TrainingMethod as TrainingMethod
from .seeding import TrajectoryFit as TrajectoryFit
from .solver import NetworkVI as NetworkVI
from .solver_state import NetworkVIState as NetworkVIState
from .spectral import SpectralCGVI as SpectralCGVI
from .spectral import spectral_degree as spectral_degree
from .spectral import spectral_step_error as spectral_step_error
from .step_size import RetryFailedSteps as RetryFailedSteps
from .terms import IODETerm as IODETerm
from .terms import LagrangianTerm as LagrangianTerm

__version__ = "0.1.0.dev0"

# The public names: those re-exported above, the public subpackages, and the symbolic pieces
# loaded on first use (`_LAZY`). Submodules bound here by their import are not among them.
_PUBLIC_MODULES = ("oga", "problems")
_PUBLIC = frozenset(
    name
    for name, value in globals().items()
    if not name.startswith("_")
    and (not isinstance(value, _types.ModuleType) or name in _PUBLIC_MODULES)
)


_LAZY = {
    "symbolic": ("diffrax_vi.symbolic", None),
    "compile_exprs": ("diffrax_vi.symbolic", "compile_exprs"),
    "sympy_activation": ("diffrax_vi.symbolic", "sympy_activation"),
    "SymbolicAnsatz": ("diffrax_vi.symbolic.ansatz", "SymbolicAnsatz"),
    "VISEBasis": ("diffrax_vi.symbolic.ansatz", "VISEBasis"),
    "SympyLagrangianTerm": ("diffrax_vi.symbolic.terms", "SympyLagrangianTerm"),
    "sympy_lagrangian_term": ("diffrax_vi.symbolic.terms", "sympy_lagrangian_term"),
}


def __getattr__(name):
    # sympy takes over a second to import; the symbolic pieces load on first use.
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        mod = importlib.import_module(module)
        return mod if attr is None else getattr(mod, attr)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(_PUBLIC | set(_LAZY))
