"""diffrax_vi: neural-network variational integrators for Lagrangian mechanics, as diffrax solvers.

The public API is `__all__` (also what `dir(diffrax_vi)` lists); the subpackages `oga` and
`problems` have their own. float64 needs `jax.config.update("jax_enable_x64", True)`; the
library never flips it.
"""

from . import oga as oga
from . import problems as problems
from ._activations import elu as elu
from ._activations import gelu as gelu
from ._activations import gelu_exact as gelu_exact
from ._activations import relu_k as relu_k
from ._activations import sigmoid as sigmoid
from ._activations import sin as sin
from ._activations import tanh as tanh
from ._ansatz import AbstractBasis as AbstractBasis
from ._ansatz import DenseNetBasis as DenseNetBasis
from ._ansatz import LagrangeBasis as LagrangeBasis
from ._ansatz import ShallowNetBasis as ShallowNetBasis
from ._ansatz.symmetry import MirrorPairs as MirrorPairs
from ._ansatz.symmetry import NoSymmetry as NoSymmetry
from ._ansatz.symmetry import SharedMirrorPairs as SharedMirrorPairs
from ._ensemble import ensemble as ensemble
from ._ensemble import ensemble_gather as ensemble_gather
from ._ensemble import ensemble_mesh as ensemble_mesh
from ._explicit import BlanesMoan as BlanesMoan
from ._explicit import Composition as Composition
from ._explicit import StormerVerlet as StormerVerlet
from ._fallback import AllParameterFallbackWarning as AllParameterFallbackWarning
from ._hidden_layers import FirstSeedLayer as FirstSeedLayer
from ._hidden_layers import SeedLayer as SeedLayer
from ._hidden_layers import UniformLayer as UniformLayer
from ._interpolation import NetworkInterpolation as NetworkInterpolation
from ._methods import CGVI as CGVI
from ._methods import VISE as VISE
from ._methods import DenseNet as DenseNet
from ._methods import ShallowNet as ShallowNet
from ._methods import ShallowNetAutodiff as ShallowNetAutodiff
from ._methods import ShallowNetAutodiffReversible as ShallowNetAutodiffReversible
from ._methods import ShallowNetReversible as ShallowNetReversible
from ._parameter_seed import FitProblem as FitProblem
from ._quadrature import GaussLegendre as GaussLegendre
from ._quadrature import Simpson as Simpson
from ._results import StepReport as StepReport
from ._results import describe_failure as describe_failure
from ._results import failure_kind as failure_kind
from ._root_finder import AbstractStepRootFinder as AbstractStepRootFinder
from ._root_finder import ChordIteration as ChordIteration
from ._root_finder import LevenbergMarquardt as LevenbergMarquardt
from ._root_finder import RegularisedNewton as RegularisedNewton
from ._root_finder import RoundoffNewton as RoundoffNewton
from ._root_finder import StepHints as StepHints
from ._seeding import LSGD as LSGD
from ._seeding import AbstractInitialTrajectory as AbstractInitialTrajectory
from ._seeding import AbstractParameterSeed as AbstractParameterSeed
from ._seeding import HermiteExtrapolation as HermiteExtrapolation
from ._seeding import InitialWeights as InitialWeights
from ._seeding import IntegratorExtrapolation as IntegratorExtrapolation
from ._seeding import LeastSquaresFit as LeastSquaresFit
from ._seeding import NoExtrapolation as NoExtrapolation
from ._seeding import PreviousStep as PreviousStep
from ._seeding import SeedPolicy as SeedPolicy
from ._seeding import TrainingMethod as TrainingMethod
from ._seeding import TrajectoryFit as TrajectoryFit
from ._solver import NetworkVI as NetworkVI
from ._solver_state import NetworkVIState as NetworkVIState
from ._spectral import SpectralCGVI as SpectralCGVI
from ._spectral import spectral_degree as spectral_degree
from ._spectral import spectral_step_error as spectral_step_error
from ._step.formulation import AbstractFormulation as AbstractFormulation
from ._step.formulation import FreeEndpoints as FreeEndpoints
from ._step.formulation import InterpolatingEndpoints as InterpolatingEndpoints
from ._step.projection import VariableProjection as VariableProjection
from ._step_size import RetryFailedSteps as RetryFailedSteps
from ._terms import IODETerm as IODETerm
from ._terms import LagrangianTerm as LagrangianTerm
from ._xla_options import compile_loops_whole as compile_loops_whole
from ._xla_options import loops_compiled_whole as loops_compiled_whole

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
    "ChordIteration",
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
    "compile_exprs": ("diffrax_vi._codegen", "compile_exprs"),
    "sympy_activation": ("diffrax_vi._codegen", "sympy_activation"),
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
