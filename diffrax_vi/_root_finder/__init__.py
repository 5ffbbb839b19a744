"""The per-step root finders and what the solver tells them about a step.

- `newton`: `RoundoffNewton`, Newton's method to round-off for the projected step's isolated
  root (the default of `VariableProjection` and `CGVI`).
- `chord`: `ChordIteration`, the chord iteration, a cheaper drop-in for it.
- `damped_newton`: `LevenbergMarquardt` and `RegularisedNewton`, for the all-parameter step's
  rank-deficient equations.
- `step_hints`: `StepHints` and `AbstractStepRootFinder`, the interface between `NetworkVI`
  and its root finder.
"""

from .chord import ChordIteration as ChordIteration
from .damped_newton import AbstractDampedNewton as AbstractDampedNewton
from .damped_newton import LevenbergMarquardt as LevenbergMarquardt
from .damped_newton import RegularisedNewton as RegularisedNewton
from .newton import RoundoffNewton as RoundoffNewton
from .step_hints import AbstractStepRootFinder as AbstractStepRootFinder
from .step_hints import StepHints as StepHints
