"""Per-step seeds of the Newton solve: initial trajectories and parameter fits."""

from .fit import (
    AbstractParameterSeed,
    FitProblem,
    InitialWeights,
    LeastSquaresFit,
    fit_network,
)
from .training import LSGD, TrainingMethod
from .trajectories import (
    AbstractInitialTrajectory,
    HermiteExtrapolation,
    IntegratorExtrapolation,
    NoExtrapolation,
    PreviousStep,
    StepHistory,
    implicit_midpoint,
)
from .trajectory_fit import TrajectoryFit

__all__ = [
    "LSGD",
    "TrainingMethod",
    "AbstractInitialTrajectory",
    "AbstractParameterSeed",
    "FitProblem",
    "HermiteExtrapolation",
    "InitialWeights",
    "IntegratorExtrapolation",
    "LeastSquaresFit",
    "NoExtrapolation",
    "PreviousStep",
    "StepHistory",
    "TrajectoryFit",
    "fit_network",
    "implicit_midpoint",
]
