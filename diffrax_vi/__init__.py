"""diffrax_vi: neural-network variational integrators for Lagrangian mechanics, as diffrax solvers.

float64 needs `jax.config.update("jax_enable_x64", True)`; the library never flips it.
"""

from . import oga, problems
from .activations import elu, gelu, relu_k, sigmoid, sin, tanh
from .ansatz import AbstractBasis, ShallowNetBasis
from .formulation import FreeEndpoints
from .interpolation import NetworkInterpolation
from .methods import ShallowNet
from .nonlinear import LevenbergMarquardt, RegularisedNewton
from .oga import OGA, OGA1d, OGA1dNormalized
from .quadrature import GaussLegendre, Simpson
from .seeding import IntegratorExtrapolation, NoExtrapolation, PreviousStep
from .solver import NetworkVI, NetworkVIState
from .terms import IODETerm, LagrangianTerm

__version__ = "0.1.0.dev0"

__all__ = [
    "AbstractBasis",
    "FreeEndpoints",
    "GaussLegendre",
    "IODETerm",
    "IntegratorExtrapolation",
    "LagrangianTerm",
    "LevenbergMarquardt",
    "NetworkInterpolation",
    "NetworkVI",
    "NetworkVIState",
    "NoExtrapolation",
    "OGA",
    "OGA1d",
    "OGA1dNormalized",
    "PreviousStep",
    "RegularisedNewton",
    "ShallowNet",
    "ShallowNetBasis",
    "Simpson",
    "elu",
    "gelu",
    "oga",
    "problems",
    "relu_k",
    "sigmoid",
    "sin",
    "tanh",
]
