"""Reference problems of NonlinearIntegrators.jl / GeometricProblems.jl as diffrax terms.

Each function returns a `Problem`: a `LagrangianTerm` or `IODETerm`, an initial state
`(q0, p0)` in the requested dtype, a default span and step, an energy for drift measurements and
a float64 reference solution.
"""

from .base import Problem
from .coupled_oscillators import coupled_oscillators
from .double_pendulum import double_pendulum
from .harmonic_oscillator import harmonic_oscillator
from .pendulum import pendulum

__all__ = [
    "Problem",
    "coupled_oscillators",
    "double_pendulum",
    "harmonic_oscillator",
    "pendulum",
]
