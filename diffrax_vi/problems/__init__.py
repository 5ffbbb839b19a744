"""Reference problems of NonlinearIntegrators.jl / GeometricProblems.jl as diffrax terms.

Each function returns a `Problem`: a `LagrangianTerm` or `IODETerm`, an initial state
`(q0, p0)` in the requested dtype, a default span and step, an energy for drift measurements and
a float64 reference solution.
"""

from .base import Problem as Problem
from .coupled_oscillators import coupled_oscillators as coupled_oscillators
from .double_pendulum import double_pendulum as double_pendulum
from .harmonic_oscillator import harmonic_oscillator as harmonic_oscillator
from .henon_heiles import henon_heiles as henon_heiles
from .kepler import kepler as kepler
from .outer_solar_system import outer_solar_system as outer_solar_system
from .pendulum import pendulum as pendulum
from .perturbed_pendulum import perturbed_pendulum as perturbed_pendulum
from .stored import StoredFlow as StoredFlow
from .toda_lattice import toda_lattice as toda_lattice
