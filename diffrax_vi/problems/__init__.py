"""Test problems of Lagrangian mechanics as diffrax terms, with stored reference solutions.

Each function returns a `Problem`: a `LagrangianTerm` or `IODETerm`, an initial state
`(q0, p0)` in the requested dtype, a default span and step, an energy for drift measurements and
a float64 reference solution. The slowly modulated (time-dependent) oscillator, the charged
particle in a non-uniform magnetic field and the stiff Fermi–Pasta–Ulam chain are the harder
ones.
"""

from .base import Problem as Problem
from .charged_particle import charged_particle as charged_particle
from .coupled_oscillators import coupled_oscillators as coupled_oscillators
from .double_pendulum import double_pendulum as double_pendulum
from .fermi_pasta_ulam import fermi_pasta_ulam as fermi_pasta_ulam
from .forced_oscillator import damped_oscillator as damped_oscillator
from .forced_oscillator import driven_oscillator as driven_oscillator
from .forced_oscillator import forced_oscillator as forced_oscillator
from .harmonic_oscillator import harmonic_oscillator as harmonic_oscillator
from .henon_heiles import henon_heiles as henon_heiles
from .kepler import kepler as kepler
from .kepler import solve_kepler_equation as solve_kepler_equation
from .modulated_oscillator import modulated_oscillator as modulated_oscillator
from .outer_solar_system import outer_solar_system as outer_solar_system
from .pendulum import pendulum as pendulum
from .perturbed_pendulum import perturbed_pendulum as perturbed_pendulum
from .rigid_chain import JointDamping as JointDamping
from .rigid_chain import chain_angles_to_state as chain_angles_to_state
from .rigid_chain import rigid_chain as rigid_chain
from .spherical_pendulum import spherical_pendulum as spherical_pendulum
from .stored import StoredFlow as StoredFlow
from .toda_lattice import toda_lattice as toda_lattice

__all__ = [
    "Problem",
    "StoredFlow",
    "charged_particle",
    "coupled_oscillators",
    "double_pendulum",
    "damped_oscillator",
    "driven_oscillator",
    "fermi_pasta_ulam",
    "forced_oscillator",
    "harmonic_oscillator",
    "henon_heiles",
    "kepler",
    "modulated_oscillator",
    "outer_solar_system",
    "pendulum",
    "perturbed_pendulum",
    "rigid_chain",
    "JointDamping",
    "chain_angles_to_state",
    "spherical_pendulum",
    "solve_kepler_equation",
    "toda_lattice",
]


def __dir__():
    return sorted(__all__)
