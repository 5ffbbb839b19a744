"""diffrax_vi: neural-network variational integrators for Lagrangian mechanics, as diffrax solvers.

The public API is `__all__` (also what `dir(diffrax_vi)` lists); the subpackages `oga` and
`problems` have their own. float64 needs `jax.config.update("jax_enable_x64", True)`; the
library never flips it.
"""

from . import oga as oga
from . import problems as problems
from ._explicit import BlanesMoan as BlanesMoan
from ._explicit import Composition as Composition
from ._explicit import StormerVerlet as StormerVerlet
from ._xla_options import compile_loops_whole as compile_loops_whole
from ._xla_options import loops_compiled_whole as loops_compiled_whole
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
from .ansatz.symmetry import MirrorPairs as MirrorPairs
from .ansatz.symmetry import NoSymmetry as NoSymmetry
from .ansatz.symmetry import SharedMirrorPairs as SharedMirrorPairs
from .ensemble import ensemble as ensemble
from .ensemble import ensemble_gather as ensemble_gather
from .ensemble import ensemble_mesh as ensemble_mesh
from .fallback import AllParameterFallbackWarning as AllParameterFallbackWarning
from .formulation import AbstractFormulation as AbstractFormulation
from .formulation import FreeEndpoints as FreeEndpoints
from .formulation import InterpolatingEndpoints as InterpolatingEndpoints
from .hidden_layers import FirstSeedLayer as FirstSeedLayer
from .hidden_layers import SeedLayer as SeedLayer
from .hidden_layers import UniformLayer as UniformLayer
from .interpolation import NetworkInterpolation as NetworkInterpolation
from .methods import CGVI as CGVI
from .methods import VISE as VISE
from .methods import DenseNet as DenseNet
from .methods import ShallowNet as ShallowNet
from .methods import ShallowNetAutodiff as ShallowNetAutodiff
from .methods import ShallowNetAutodiffReversible as ShallowNetAutodiffReversible
from .methods import ShallowNetReversible as ShallowNetReversible
from .parameter_seed import FitProblem as FitProblem
from .projection import VariableProjection as VariableProjection
from .quadrature import GaussLegendre as GaussLegendre
from .quadrature import Simpson as Simpson
from .results import StepReport as StepReport
from .results import describe_failure as describe_failure
from .results import failure_kind as failure_kind
from .root_finders import AbstractStepRootFinder as AbstractStepRootFinder
from .root_finders import FixedPointIteration as FixedPointIteration
from .root_finders import LevenbergMarquardt as LevenbergMarquardt
from .root_finders import RegularisedNewton as RegularisedNewton
from .root_finders import RoundoffNewton as RoundoffNewton
from .root_finders import StepHints as StepHints
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

__all__ = [
    # Solver, method constructors, step-size control
    "NetworkVI",
    "NetworkVIState",
    "NetworkInterpolation",
    "AllParameterFallbackWarning",
    "CGVI",
    "DenseNet",
    "ShallowNet",
    "ShallowNetAutodiff",
    "ShallowNetAutodiffReversible",
    "ShallowNetReversible",
    "VISE",
    "SpectralCGVI",
    "spectral_degree",
    "spectral_step_error",
    "RetryFailedSteps",
    # Explicit symplectic solvers (separable Lagrangians)
    "StormerVerlet",
    "Composition",
    "BlanesMoan",
    "compile_loops_whole",
    "loops_compiled_whole",
    # Terms and quadrature
    "LagrangianTerm",
    "IODETerm",
    "SympyLagrangianTerm",
    "sympy_lagrangian_term",
    "GaussLegendre",
    "Simpson",
    # Ansätze, their symmetries, activations
    "AbstractBasis",
    "ShallowNetBasis",
    "DenseNetBasis",
    "LagrangeBasis",
    "SymbolicAnsatz",
    "VISEBasis",
    "NoSymmetry",
    "MirrorPairs",
    "SharedMirrorPairs",
    "tanh",
    "sigmoid",
    "sin",
    "gelu",
    "gelu_exact",
    "elu",
    "relu_k",
    # sympy compiled to JAX
    "compile_exprs",
    "sympy_activation",
    # Formulations
    "AbstractFormulation",
    "FreeEndpoints",
    "InterpolatingEndpoints",
    "VariableProjection",
    "UniformLayer",
    "FirstSeedLayer",
    "SeedLayer",
    # Root finders
    "StepHints",
    "AbstractStepRootFinder",
    "LevenbergMarquardt",
    "RegularisedNewton",
    "RoundoffNewton",
    "FixedPointIteration",
    # Seeds
    "SeedPolicy",
    "AbstractInitialTrajectory",
    "IntegratorExtrapolation",
    "HermiteExtrapolation",
    "NoExtrapolation",
    "PreviousStep",
    "AbstractParameterSeed",
    "FitProblem",
    "LSGD",
    "TrainingMethod",
    "LeastSquaresFit",
    "InitialWeights",
    "TrajectoryFit",
    # Failures
    "failure_kind",
    "describe_failure",
    "StepReport",
    # Ensembles
    "ensemble",
    "ensemble_mesh",
    "ensemble_gather",
    # Subpackages
    "oga",
    "problems",
]

# sympy takes over a second to import: the pieces written with it load on first use.
_LAZY = {
    "compile_exprs": ("diffrax_vi.codegen", "compile_exprs"),
    "sympy_activation": ("diffrax_vi.codegen", "sympy_activation"),
    "SymbolicAnsatz": ("diffrax_vi.symbolic.ansatz", "SymbolicAnsatz"),
    "VISEBasis": ("diffrax_vi.symbolic.ansatz", "VISEBasis"),
    "SympyLagrangianTerm": ("diffrax_vi.symbolic.terms", "SympyLagrangianTerm"),
    "sympy_lagrangian_term": ("diffrax_vi.symbolic.terms", "sympy_lagrangian_term"),
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    if name == "symbolic":  # a submodule, reachable as an attribute like the others
        import importlib

        return importlib.import_module("diffrax_vi.symbolic")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    # Submodules bound by their import are attributes too, but not public names.
    return sorted(__all__)
