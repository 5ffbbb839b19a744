"""Reference problems of NonlinearIntegrators.jl / GeometricProblems.jl as diffrax terms.

Each function returns a `Problem`: a `LagrangianTerm` or `IODETerm`, an initial state
`(q0, p0)` in the requested dtype, a default span and step, an energy for drift measurements and
a float64 reference solution.
"""

from .base import Problem
from .coupled_oscillators import coupled_oscillators
from .double_pendulum import double_pendulum
from .harmonic_oscillator import harmonic_oscillator
from .henon_heiles import henon_heiles
from .kepler import kepler
from .outer_solar_system import outer_solar_system
from .pendulum import pendulum
from .perturbed_pendulum import perturbed_pendulum
from .stored import StoredFlow
from .toda_lattice import toda_lattice

__all__ = [
    "Problem",
    "coupled_oscillators",
    "double_pendulum",
    "harmonic_oscillator",
    "henon_heiles",
    "kepler",
    "outer_solar_system",
    "pendulum",
    "perturbed_pendulum",
    "StoredFlow",
    "toda_lattice",
]
