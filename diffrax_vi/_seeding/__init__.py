"""Per-step seeds of the Newton solve: the seed policy, initial trajectories and parameter
fits (the OGA fits are in `diffrax_vi.oga`)."""

from .._parameter_seed import AbstractParameterSeed as AbstractParameterSeed
from .._parameter_seed import FitProblem as FitProblem
from .fit import InitialWeights as InitialWeights
from .fit import LeastSquaresFit as LeastSquaresFit
from .policy import SeedPolicy as SeedPolicy
from .training import LSGD as LSGD
from .training import TrainingMethod as TrainingMethod
from .trajectories import AbstractInitialTrajectory as AbstractInitialTrajectory
from .trajectories import HermiteExtrapolation as HermiteExtrapolation
from .trajectories import IntegratorExtrapolation as IntegratorExtrapolation
from .trajectories import NoExtrapolation as NoExtrapolation
from .trajectories import PreviousStep as PreviousStep
from .trajectories import StepHistory as StepHistory
from .trajectories import implicit_midpoint as implicit_midpoint
from .trajectory_fit import TrajectoryFit as TrajectoryFit
