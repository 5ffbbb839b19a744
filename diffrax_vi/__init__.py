"""diffrax_vi: neural-network variational integrators for Lagrangian mechanics, as diffrax solvers.

float64 needs `jax.config.update("jax_enable_x64", True)`; the library never flips it.
"""

from . import oga, problems
from .activations import elu, gelu, relu_k, sigmoid, sin, tanh
from .ansatz import AbstractBasis, DenseNetBasis, LagrangeBasis, ShallowNetBasis
from .ensemble import ensemble, ensemble_gather, ensemble_mesh
from .fixed_point import FixedPointIteration
from .formulation import AbstractFormulation, FreeEndpoints, InterpolatingEndpoints
from .interpolation import NetworkInterpolation
from .methods import (
    CGVI,
    VISE,
    DenseNet,
    ShallowNet,
    ShallowNetAutodiff,
    ShallowNetAutodiffReversible,
    ShallowNetReversible,
)
from .nonlinear import LevenbergMarquardt, RegularisedNewton
from .oga import (
    OGA,
    AngularGrid,
    BiasGrid1d,
    IncrementalQR,
    MirrorPairs,
    NormalEquationsFit,
    NormalizedProjection,
    NoSymmetry,
    OGA1d,
    OGA1dNormalEquations,
    OGA1dNormalized,
    OGA1dStable,
    OGA2d,
    OGASphere,
    OrthogonalProjection,
    PivotedQR,
    RawProjection,
    Refined,
    SharedMirrorPairs,
    TruncatedSVD,
    WeightBiasGrid2d,
    WeightedQR,
    oga_fit,
)
from .projection import (
    FirstSeedLayer,
    RoundoffNewton,
    SeedLayer,
    UniformLayer,
    VariableProjection,
)
from .quadrature import GaussLegendre, Simpson
from .results import StepReport, describe_failure, failure_kind
from .seeding import (
    LSGD,
    AbstractInitialTrajectory,
    AbstractParameterSeed,
    HermiteExtrapolation,
    InitialWeights,
    IntegratorExtrapolation,
    LeastSquaresFit,
    NoExtrapolation,
    PreviousStep,
    TrainingMethod,
    TrajectoryFit,
)
from .solver import NetworkVI
from .solver_state import NetworkVIState
from .spectral import SpectralCGVI, spectral_degree, spectral_step_error
from .step_size import RetryFailedSteps
from .terms import IODETerm, LagrangianTerm

__version__ = "0.1.0.dev0"

__all__ = [
    "ensemble",
    "ensemble_gather",
    "ensemble_mesh",
    "DenseNet",
    "DenseNetBasis",
    "LSGD",
    "TrainingMethod",
    "AbstractBasis",
    "AbstractFormulation",
    "AbstractInitialTrajectory",
    "AbstractParameterSeed",
    "CGVI",
    "HermiteExtrapolation",
    "InitialWeights",
    "InterpolatingEndpoints",
    "LagrangeBasis",
    "LeastSquaresFit",
    "ShallowNetAutodiff",
    "ShallowNetAutodiffReversible",
    "ShallowNetReversible",
    "TrajectoryFit",
    "SymbolicAnsatz",
    "SympyLagrangianTerm",
    "VISE",
    "VISEBasis",
    "compile_exprs",
    "symbolic",
    "sympy_activation",
    "sympy_lagrangian_term",
    "AngularGrid",
    "BiasGrid1d",
    "FreeEndpoints",
    "VariableProjection",
    "RoundoffNewton",
    "FixedPointIteration",
    "SpectralCGVI",
    "spectral_degree",
    "spectral_step_error",
    "UniformLayer",
    "FirstSeedLayer",
    "SeedLayer",
    "GaussLegendre",
    "IODETerm",
    "IncrementalQR",
    "IntegratorExtrapolation",
    "LagrangianTerm",
    "LevenbergMarquardt",
    "MirrorPairs",
    "NetworkInterpolation",
    "NetworkVI",
    "NetworkVIState",
    "StepReport",
    "describe_failure",
    "failure_kind",
    "NoExtrapolation",
    "NoSymmetry",
    "NormalEquationsFit",
    "NormalizedProjection",
    "OGA",
    "OGA1d",
    "OGA1dNormalEquations",
    "OGA1dNormalized",
    "OGA1dStable",
    "OGA2d",
    "OGASphere",
    "OrthogonalProjection",
    "PivotedQR",
    "PreviousStep",
    "RawProjection",
    "Refined",
    "RegularisedNewton",
    "RetryFailedSteps",
    "ShallowNet",
    "ShallowNetBasis",
    "SharedMirrorPairs",
    "Simpson",
    "TruncatedSVD",
    "WeightBiasGrid2d",
    "WeightedQR",
    "elu",
    "gelu",
    "oga",
    "oga_fit",
    "problems",
    "relu_k",
    "sigmoid",
    "sin",
    "tanh",
]


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
