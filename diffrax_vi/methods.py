"""The reference's method names as constructors of a configured `NetworkVI`.

A user of NonlinearIntegrators.jl writes `ShallowNet(basis, quadrature; kwargs...)`; here the
same call returns a `NetworkVI`. The reference's keyword names are accepted (and translated);
anything else is refused by name.
"""

from __future__ import annotations

import math
from typing import Any

from .ansatz.shallow import ShallowNetBasis
from .nonlinear import RegularisedNewton
from .oga import OGA
from .quadrature import AbstractQuadrature
from .seeding.trajectories import (
    AbstractInitialTrajectory,
    IntegratorExtrapolation,
    NoExtrapolation,
    PreviousStep,
)
from .solver import NetworkVI

__all__ = ["ShallowNet"]

_SOLVER_OPTIONS = {"root_finder", "root_find_max_steps", "adjoint"}


def _with_substeps(trajectory: AbstractInitialTrajectory, substeps: int):
    if isinstance(trajectory, PreviousStep):
        return PreviousStep(first=_with_substeps(trajectory.first, substeps))
    if isinstance(trajectory, IntegratorExtrapolation):
        return IntegratorExtrapolation(substeps, trajectory.newton_iterations)
    if isinstance(trajectory, NoExtrapolation):
        return NoExtrapolation(substeps)
    return trajectory


def ShallowNet(
    basis: ShallowNetBasis,
    quadrature: AbstractQuadrature,
    *,
    extrapolation_substep: int | None = None,
    initial_trajectory_method: AbstractInitialTrajectory | None = None,
    initial_guess_method: OGA | None = None,
    bias_interval: tuple[float, float] = (-math.pi, math.pi),
    dict_amount: int = 4000,
    regularization_factor: float | None = None,
    max_iterations: int | None = None,
    **options: Any,
) -> NetworkVI:
    """The reference's `ShallowNet`: a shallow network with free endpoints, seeded by OGA.

    **Arguments:**

    - `basis`: a `ShallowNetBasis(activation, width)`.
    - `quadrature`: e.g. `GaussLegendre(8)`.
    - `extrapolation_substep`: sub-steps of the initial trajectory (even; default 10).
    - `initial_trajectory_method`: `IntegratorExtrapolation()` (default), `NoExtrapolation()`
      or `PreviousStep()`.
    - `initial_guess_method`: an OGA configuration (default `OGA1d()`).
    - `bias_interval`, `dict_amount`: the OGA dictionary (defaults `(-π, π)`, 4000).
    - `regularization_factor`: if given, use `RegularisedNewton(lam=regularization_factor)`,
      the reference's Newton with a diagonal shift, instead of the default root finder.
    - `max_iterations`: iteration cap per step (`root_find_max_steps`).
    - `**options`: `root_finder`, `root_find_max_steps`, `adjoint` of `NetworkVI`.
    """
    if not isinstance(basis, ShallowNetBasis):
        raise TypeError(f"ShallowNet needs a ShallowNetBasis, got {basis!r}")
    unknown = set(options) - _SOLVER_OPTIONS
    if unknown:
        raise TypeError(
            f"ShallowNet got unknown option(s) {sorted(unknown)}; accepted: extrapolation_substep, "
            "initial_trajectory_method, initial_guess_method, bias_interval, dict_amount, "
            f"regularization_factor, max_iterations, {', '.join(sorted(_SOLVER_OPTIONS))}"
        )
    kwargs: dict[str, Any] = dict(options)
    trajectory = initial_trajectory_method or IntegratorExtrapolation()
    if extrapolation_substep is not None:
        trajectory = _with_substeps(trajectory, extrapolation_substep)
    kwargs["initial_trajectory"] = trajectory
    if initial_guess_method is not None:
        kwargs["initial_guess"] = initial_guess_method
    if regularization_factor is not None:
        if "root_finder" in options:
            raise TypeError("give either regularization_factor or root_finder, not both")
        kwargs["root_finder"] = RegularisedNewton(lam=regularization_factor)
    if max_iterations is not None:
        kwargs["root_find_max_steps"] = max_iterations
    return NetworkVI(
        basis,
        quadrature,
        bias_interval=tuple(float(b) for b in bias_interval),
        dict_amount=dict_amount,
        **kwargs,
    )


