"""Per-step seeds of the Newton solve: initial trajectories and parameter fits."""

from .trajectories import (
    AbstractInitialTrajectory,
    IntegratorExtrapolation,
    NoExtrapolation,
    PreviousStep,
    implicit_midpoint,
)

__all__ = [
    "AbstractInitialTrajectory",
    "IntegratorExtrapolation",
    "NoExtrapolation",
    "PreviousStep",
    "implicit_midpoint",
]
