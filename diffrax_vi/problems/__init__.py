"""Reference problems of NonlinearIntegrators.jl / GeometricProblems.jl as diffrax terms.

Each function returns a `Problem`: a `LagrangianTerm` or `IODETerm`, an initial state
`(q0, p0)` in the requested dtype, a default span and step, an energy for drift measurements and
a float64 reference solution. Three harder problems have no counterpart in the reference package:
a slowly modulated (time-dependent) oscillator, a charged particle in a non-uniform magnetic
field and the stiff Fermi–Pasta–Ulam chain.
"""

from .base import Problem as Problem
from .charged_particle import charged_particle as charged_particle
from .coupled_oscillators import coupled_oscillators as coupled_oscillators
from .double_pendulum import double_pendulum as double_pendulum
from .fermi_pasta_ulam import fermi_pasta_ulam as fermi_pasta_ulam
from .harmonic_oscillator import harmonic_oscillator as harmonic_oscillator
from .henon_heiles import henon_heiles as henon_heiles
from .kepler import kepler as kepler
from .modulated_oscillator import modulated_oscillator as modulated_oscillator
from .outer_solar_system import outer_solar_system as outer_solar_system
from .pendulum import pendulum as pendulum
from .perturbed_pendulum import perturbed_pendulum as perturbed_pendulum
from .stored import StoredFlow as StoredFlow
from .toda_lattice import toda_lattice as toda_lattice
