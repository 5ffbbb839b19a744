"""Checks of `NetworkVI`'s options that are not about seeding (those are
`SeedPolicy.check`): types, the quadrature against the ansatz, and the
formulation against the root finder."""

from __future__ import annotations

import warnings
from typing import Any

import optimistix as optx

from ._ansatz.base import AbstractBasis
from ._quadrature import AbstractQuadrature
from ._root_finder.damped_newton import AbstractDampedNewton
from ._root_finder.newton import RoundoffNewton
from ._root_finder.step_hints import AbstractStepRootFinder, missing_hints
from ._step.companion import check_error_estimate
from ._step.formulation import AbstractFormulation, FreeEndpoints
from ._step.projection import VariableProjection

__all__ = ["check_options"]


def check_options(solver: Any) -> None:
    """Raise a `TypeError` or `ValueError` naming the first option of `solver` (a `NetworkVI`)
    that is wrong."""
    if not isinstance(solver.basis, AbstractBasis):
        raise TypeError(f"basis must be an ansatz such as ShallowNetBasis, got {solver.basis!r}")
    if not isinstance(solver.quadrature, AbstractQuadrature):
        raise TypeError(
            f"quadrature must be a rule such as GaussLegendre(8), got {solver.quadrature!r}"
        )
    if not isinstance(solver.formulation, AbstractFormulation):
        raise TypeError(
            "formulation must be FreeEndpoints(), InterpolatingEndpoints() or "
            f"VariableProjection(), got {solver.formulation!r}"
        )
    if not isinstance(solver.root_finder, optx.AbstractRootFinder):
        raise TypeError(
            "root_finder must be an optimistix root finder such as RoundoffNewton() or "
            f"LevenbergMarquardt(), got {solver.root_finder!r}"
        )
    if not isinstance(solver.root_finder, AbstractStepRootFinder):
        lacks = "; ".join(missing_hints(solver.root_finder).values())
        warnings.warn(
            f"{type(solver.root_finder).__name__} does not read NetworkVI's step hints, so it "
            f"solves each step without: {lacks}. LevenbergMarquardt(), RegularisedNewton(), "
            "RoundoffNewton() and ChordIteration() read them.",
            UserWarning,
            stacklevel=4,
        )
    if not isinstance(solver.compensated, bool):
        raise TypeError(f"compensated must be True or False, got {solver.compensated!r}")
    if not isinstance(solver.energy_check, bool):
        raise TypeError(f"energy_check must be True or False, got {solver.energy_check!r}")
    need = solver.basis.min_nodes()
    if solver.quadrature.num_nodes < need:
        raise ValueError(
            f"{solver.basis!r} needs a quadrature with at least {need} nodes; "
            f"{solver.quadrature!r} has {solver.quadrature.num_nodes}. With fewer, the step "
            "equations do not determine the step."
        )
    check_error_estimate(solver.error_estimate, solver.basis)
    if isinstance(solver.formulation, VariableProjection):
        solver.formulation.check_basis(solver.basis)
        if not isinstance(solver.root_finder, RoundoffNewton):
            raise ValueError(
                "VariableProjection() solves a square system with an isolated root: use "
                "root_finder=RoundoffNewton() (the default) or ChordIteration(), got "
                f"{solver.root_finder!r}"
            )
    if (
        isinstance(solver.root_finder, AbstractDampedNewton)
        and solver.root_finder.jacobian == "structured"
        and not (isinstance(solver.formulation, FreeEndpoints) and solver.basis.coordinatewise)
    ):
        raise ValueError(
            "jacobian='structured' assembles the Jacobian by coordinate blocks, which needs "
            "free endpoints and a basis whose coordinates have their own parameters "
            f"(ShallowNetBasis, LagrangeBasis); got {solver.basis!r} with "
            f"{type(solver.formulation).__name__}"
        )
    if not isinstance(solver.iteration_log, int) or solver.iteration_log < 0:
        raise ValueError(
            f"iteration_log must be a non-negative integer, got {solver.iteration_log!r}"
        )
    cap = solver.root_find_max_steps
    if not isinstance(cap, int) or cap < 1:
        raise ValueError(f"root_find_max_steps must be a positive integer, got {cap!r}")
