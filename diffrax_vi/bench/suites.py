"""The published benchmark configurations (`--quick` and `--full`): problems, spans, solvers
and sweeps. Everything here is float64."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import diffrax
import jax.numpy as jnp

from .. import problems as _problems
from .._activations import gelu, tanh
from .._ansatz.shallow import ShallowNetBasis
from .._explicit import AbstractSplittingSolver, BlanesMoan, Composition
from .._methods import CGVI
from .._quadrature import GaussLegendre
from .._root_finder.damped_newton import LevenbergMarquardt
from .._seeding.policy import SeedPolicy
from .._seeding.trajectories import IntegratorExtrapolation, PreviousStep
from .._solver import NetworkVI
from .._step.formulation import FreeEndpoints
from .._step.projection import VariableProjection
from .entries import Adaptive, Entry, Fixed, Heyoka, SciPy
from .peers import heyoka_available

__all__ = ["Setting", "SETTINGS", "PEERS_ADAPTIVE", "networkvi_entries", "energy_entries",
           "peer_entries"]


@dataclasses.dataclass(frozen=True)
class Setting:
    """How one problem is benchmarked.

    - `make`: builds the float64 `Problem` with the work-precision span.
    - `width`, `nodes`: the NetworkVI network width S and Gauss–Legendre nodes R.
    - `steps`: step counts of the fixed-step sweeps (NetworkVI, CGVI) over the span.
    - `sie_steps`: step counts of `SemiImplicitEuler` (first order, so many more).
    - `long_dt`: the step of the long-time energy runs.
    - `quick_energy`: whether `--quick` runs the energy study on this problem (not for the
      Toda lattice: its NetworkVI step costs seconds, so 10⁴ steps take hours).
    """

    make: Callable
    width: int
    nodes: int
    steps: tuple[int, ...]
    sie_steps: tuple[int, ...]
    long_dt: float
    quick_energy: bool = True


def _f64(make, **kw):
    return lambda: make(dtype=jnp.float64, **kw)


SETTINGS: dict[str, Setting] = {
    "harmonic_oscillator": Setting(
        _f64(_problems.harmonic_oscillator, t1=10.0), 10, 8, (10, 20, 40, 100),
        (100, 1000, 10_000, 100_000), 0.25),
    "pendulum": Setting(
        _f64(_problems.pendulum, t1=10.0), 8, 8, (20, 40, 100), (100, 1000, 10_000), 0.1),
    "double_pendulum": Setting(
        _f64(_problems.double_pendulum, t1=2.0), 10, 16, (20, 40, 100),
        (100, 1000, 10_000), 0.05),
    # T = 2: a NetworkVI step of the 16-particle lattice (400 unknowns, dense Jacobian) takes
    # 2-4 s on the 2-core CI machine.
    "toda_lattice": Setting(
        _f64(_problems.toda_lattice, t1=2.0), 8, 16, (5, 10, 20),
        (100, 1000, 10_000, 100_000), 0.1, quick_energy=False),
    "henon_heiles": Setting(
        _f64(_problems.henon_heiles, t1=10.0), 10, 8, (20, 50, 100),
        (100, 1000, 10_000, 100_000), 0.1),
    "kepler": Setting(
        _f64(_problems.kepler, eccentricity=0.5, t1=2 * math.pi), 10, 8, (32, 64, 128),
        (1000, 10_000, 100_000), 2 * math.pi / 64),
}

QUICK_RTOLS = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
FULL_RTOLS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13)
PEERS_ADAPTIVE = ("Tsit5", "Dopri8")
# heyoka's tolerances (it reaches round-off, so the grid goes further than the others').
QUICK_HEYOKA_TOLS = (1e-6, 1e-9, 1e-12, 1e-15)
FULL_HEYOKA_TOLS = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 1e-13, 1e-14, 1e-15, 1e-16)


def networkvi_entries(setting: Setting, full: bool) -> list[Fixed]:
    """NetworkVI variants. Quick has three tanh networks: `warm` (the all-parameter step with a
    warm start from the previous step's curve), `fast` (the opt-in settings of the how-to "A faster
    step": the previous step's neurons refitted as seed, the closed-form Jacobian, a solve
    ended by the first exact iteration whose outputs settled) and `projection` (the projected
    step, `NetworkVI`'s default: `VariableProjection()` with the fixed `UniformLayer()`
    hidden layer and `RoundoffNewton()`). Full adds the all-parameter step with the
    reference's per-step seed (extrapolated trajectory + OGA) and a GELU network (warm)."""
    basis = ShallowNetBasis(tanh, setting.width)
    quad = GaussLegendre(setting.nodes)
    label = f"tanh{setting.width} R{setting.nodes}"
    out = [
        Fixed(f"NetworkVI {label} warm",
              NetworkVI(basis, quad, seed=SeedPolicy(initial_trajectory=PreviousStep())),
              family="ours"),
        Fixed(f"NetworkVI {label} fast",
              NetworkVI(basis, quad, seed=SeedPolicy(reuse_neurons=True),
                        root_finder=LevenbergMarquardt(jacobian="auto", settle=0,
                                                       otol=2.0**-39)),
              family="ours"),
        Fixed(f"NetworkVI {label} projection",
              NetworkVI(basis, quad, formulation=VariableProjection()), family="ours"),
    ]
    if full:
        out += [
            Fixed(f"NetworkVI {label} OGA",
                  NetworkVI(basis, quad,
                            seed=SeedPolicy(initial_trajectory=IntegratorExtrapolation()),
                            formulation=FreeEndpoints()),
                  family="ours"),
            Fixed(f"NetworkVI gelu{setting.width} R{setting.nodes} warm",
                  NetworkVI(ShallowNetBasis(gelu, setting.width), quad,
                            seed=SeedPolicy(initial_trajectory=PreviousStep())), family="ours"),
        ]
    return out


def energy_entries(setting: Setting) -> list[Fixed]:
    """NetworkVI in the long-time energy study: `warm` (as in the work-precision study) and
    `long-run`, the how-to's setting for long runs: refitted neurons as seed, but only after
    a step accepted at a residual of at most `2048·eps` (else the OGA), with the default
    stopping rule and the closed-form Jacobian."""
    basis = ShallowNetBasis(tanh, setting.width)
    quad = GaussLegendre(setting.nodes)
    label = f"tanh{setting.width} R{setting.nodes}"
    eps = float(jnp.finfo(jnp.float64).eps)
    return [
        networkvi_entries(setting, False)[0],
        Fixed(f"NetworkVI {label} long-run",
              NetworkVI(basis, quad,
                        seed=SeedPolicy(reuse_neurons=True, refit_residual=2048 * eps),
                        root_finder=LevenbergMarquardt(jacobian="auto")),
              family="ours"),
    ]


def peer_entries(full: bool) -> list[Entry]:
    """The peers: diffrax Tsit5, Dopri8, Kvaerno5 (PID), SemiImplicitEuler (separable problems
    only), scipy DOP853, heyoka's Taylor integrator where heyoka is installed (the `peers`
    extra), our polynomial CGVI (degree 7 on Gauss–Legendre(8), order 14) and the package's
    two fastest explicit splittings on Kepler (`BlanesMoan(6)`, `Composition(8, "kahan_li")`;
    they refuse a Lagrangian that is not separable, which is then an error row)."""
    out: list[Entry] = [
        Adaptive("Tsit5", diffrax.Tsit5()),
        Adaptive("Dopri8", diffrax.Dopri8()),
        Adaptive("Kvaerno5", diffrax.Kvaerno5()),
        Fixed("SemiImplicitEuler", diffrax.SemiImplicitEuler(), separable=True),
        SciPy("scipy DOP853", "DOP853"),
        Fixed("CGVI(7)", CGVI(7, GaussLegendre(8))),
        Fixed("BlanesMoan(6)", BlanesMoan(6)),
        Fixed("Composition(8, kahan_li)", Composition(8, "kahan_li")),
    ]
    if heyoka_available():
        out.insert(5, Heyoka("heyoka"))
    if full:
        out.append(Fixed("CGVI(4)", CGVI(4)))
    return out


def sweeps(name: str, entries: Sequence[Entry], full: bool) -> tuple[dict, dict]:
    """Step counts and tolerances per entry for a problem."""
    setting = SETTINGS[name]
    steps, rtols = {}, {}
    for e in entries:
        if isinstance(e, Fixed) and isinstance(e.solver, AbstractSplittingSolver):
            # an explicit step costs microseconds and is of lower order than CGVI(7): more
            # steps, up to round-off
            mult = (2, 4, 8, 16, 32, 64) if full else (2, 8, 32)
            steps[e.name] = tuple(sorted({m * s for s in setting.steps for m in mult}))
        elif isinstance(e, Fixed):
            base = setting.sie_steps if e.separable else setting.steps
            if full and not e.separable:
                base = tuple(sorted({*base, *(2 * s for s in base), max(base) * 4}))
            steps[e.name] = base
        elif isinstance(e, Heyoka):
            rtols[e.name] = FULL_HEYOKA_TOLS if full else QUICK_HEYOKA_TOLS
        else:
            rtols[e.name] = FULL_RTOLS if full else QUICK_RTOLS
    return steps, rtols
