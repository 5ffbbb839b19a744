"""The reference's method names as constructors of a configured `NetworkVI`.

A user of NonlinearIntegrators.jl writes `ShallowNet(basis, quadrature; kwargs...)`; here the
same call returns a `NetworkVI`. Each name is a point in the solver's axes:

| name | formulation | ansatz | default seed |
|---|---|---|---|
| `ShallowNet` | free endpoints | `ShallowNetBasis` | `OGA1d()` |
| `ShallowNetAutodiff` | interpolating | `ShallowNetBasis` | `OGA1dNormalized()` |
| `ShallowNetReversible` | free endpoints | mirrored pairs, own output weights | `OGA1d()` |
| `ShallowNetAutodiffReversible` | interpolating | mirrored pairs, own or shared α | `OGA1d()` |
| `DenseNet` | free endpoints | `DenseNetBasis` | `LSGD()` |
| `VISE` | free endpoints | `SymbolicAnsatz` | `InitialWeights(init_w)` |
| `CGVI` | free endpoints | `LagrangeBasis` | `LeastSquaresFit()` |

The reference's keyword names are accepted (and translated); anything else is refused by name.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from ._ansatz.base import AbstractBasis
from ._ansatz.dense import DenseNetBasis
from ._ansatz.polynomial import LagrangeBasis
from ._ansatz.shallow import ShallowNetBasis
from ._ansatz.symmetry import MirrorPairs, SharedMirrorPairs
from ._parameter_seed import AbstractParameterSeed
from ._quadrature import AbstractQuadrature, GaussLegendre
from ._root_finder.chord import ChordIteration
from ._root_finder.damped_newton import AbstractDampedNewton, RegularisedNewton
from ._seeding.fit import InitialWeights, LeastSquaresFit
from ._seeding.policy import SeedPolicy
from ._seeding.training import LSGD
from ._seeding.trajectories import (
    IntegratorExtrapolation,
)
from ._solver import NetworkVI
from ._step.formulation import AbstractFormulation, FreeEndpoints, InterpolatingEndpoints
from ._step.projection import VariableProjection
from .oga import OGA, OGA1d, OGA1dNormalized

__all__ = [
    "CGVI",
    "DenseNet",
    "ShallowNet",
    "ShallowNetAutodiff",
    "ShallowNetAutodiffReversible",
    "ShallowNetReversible",
    "VISE",
]

_SOLVER_OPTIONS = {"root_finder", "root_find_max_steps", "adjoint", "compensated",
                   "energy_check"}
# The step-size controller's error estimate, for every method (`NetworkVI.error_estimate`).
_SOLVER_OPTIONS |= {"error_estimate"}
# Accepted for compatibility; dense output is the continuous converged curve and nothing
# prints inside a compiled solve, so these have no effect.
_NO_EFFECT = {"record_grid_points", "show_status"}
_KNOWN = {
    "extrapolation_substep",
    "initial_trajectory_method",
    "initial_guess_method",
    "bias_interval",
    "dict_amount",
    "regularization_factor",
    "max_iterations",
    "training_epochs",
}


def _check_options(name: str, options: dict[str, Any]) -> None:
    unknown = set(options) - _KNOWN - _SOLVER_OPTIONS - _NO_EFFECT
    if unknown:
        raise TypeError(
            f"{name} got unknown option(s) {sorted(unknown)}; accepted: "
            f"{', '.join(sorted(_KNOWN | _SOLVER_OPTIONS | _NO_EFFECT))}"
        )


def _build(
    name: str,
    basis: AbstractBasis,
    quadrature: AbstractQuadrature,
    formulation: AbstractFormulation,
    default_guess: OGA | AbstractParameterSeed,
    options: dict[str, Any],
) -> NetworkVI:
    if not isinstance(quadrature, AbstractQuadrature):
        raise TypeError(
            f"{name} needs a quadrature rule such as GaussLegendre(8), got {quadrature!r}"
        )
    _check_options(name, options)
    kwargs: dict[str, Any] = {k: v for k, v in options.items() if k in _SOLVER_OPTIONS}
    trajectory = options.get("initial_trajectory_method") or IntegratorExtrapolation()
    if options.get("extrapolation_substep") is not None:
        trajectory = trajectory.with_substeps(options["extrapolation_substep"])
    guess = options.get("initial_guess_method") or default_guess
    epochs = options.get("training_epochs")
    if epochs is not None and hasattr(guess, "epochs"):
        guess = dataclasses.replace(guess, epochs=epochs)
    if options.get("regularization_factor") is not None:
        if "root_finder" in options:
            raise TypeError(f"{name}: give either regularization_factor or root_finder, not both")
        kwargs["root_finder"] = RegularisedNewton(lam=options["regularization_factor"])
    if options.get("max_iterations") is not None:
        kwargs["root_find_max_steps"] = options["max_iterations"]
    dictionary = {k: options[k] for k in ("bias_interval", "dict_amount") if k in options}
    if dictionary:
        try:
            guess = guess.with_dictionary(**dictionary)
        except TypeError as error:
            raise TypeError(f"{name}: {error}") from None
    return NetworkVI(
        basis,
        quadrature,
        formulation=formulation,
        seed=SeedPolicy(initial_trajectory=trajectory, initial_guess=guess),
        **kwargs,
    )


def _shallow(name: str, basis, symmetry=None) -> ShallowNetBasis:
    if not isinstance(basis, ShallowNetBasis):
        raise TypeError(f"{name} needs a ShallowNetBasis, got {basis!r}")
    if symmetry is None or type(basis.symmetry) is type(symmetry):
        return basis
    if basis.width % 2:
        raise ValueError(
            f"{name} places neurons in mirrored pairs, so the width must be even; got "
            f"width={basis.width}"
        )
    return ShallowNetBasis(basis.activation, basis.width, symmetry)


_SHARED_DOC = """
    **Options** (the reference's keywords):

    - `extrapolation_substep`: sub-steps of the initial trajectory (even; default 10).
    - `initial_trajectory_method`: `IntegratorExtrapolation()` (default),
      `HermiteExtrapolation()`, `NoExtrapolation()` or `PreviousStep()`.
    - `initial_guess_method`: the parameter seed (default as in the table of this module).
    - `bias_interval`, `dict_amount`: the OGA dictionary (defaults `(-π, π)`, 4000).
    - `regularization_factor`: use `RegularisedNewton(lam=...)`, the reference's Newton with a
      diagonal shift, instead of the default Levenberg–Marquardt.
    - `max_iterations`: iteration cap per step (`root_find_max_steps`).
    - `training_epochs`: epochs of a training seed (`LSGD`, `TrainingMethod`).
    - `record_grid_points`, `show_status`: accepted, no effect (dense output is the
      continuous converged curve).
    - `root_finder`, `root_find_max_steps`, `adjoint`: passed to `NetworkVI`.
"""


def ShallowNet(basis: ShallowNetBasis, quadrature: AbstractQuadrature, **options: Any) -> NetworkVI:
    """Shallow network with free endpoints (unknowns `θ`, `p_{n+1}`), seeded by `OGA1d()`."""
    return _build(
        "ShallowNet", _shallow("ShallowNet", basis), quadrature, FreeEndpoints(), OGA1d(), options
    )


def ShallowNetAutodiff(
    basis: ShallowNetBasis, quadrature: AbstractQuadrature, **options: Any
) -> NetworkVI:
    """Shallow network with interpolating endpoints: `q_h(τ) = (1−τ) q_n + τ q_{n+1} +
    τ(1−τ) N(τ)`, unknowns `θ`, `q_{n+1}`; seeded by `OGA1dNormalized()` fitted to the
    deviation from the chord with `τ(1−τ)`-modulated atoms. Exactly continuous dense output.
    (The reference's name refers to its ForwardDiff derivatives; here every ansatz is
    differentiated by JAX or by sympy, whatever the formulation.)"""
    return _build(
        "ShallowNetAutodiff",
        _shallow("ShallowNetAutodiff", basis),
        quadrature,
        InterpolatingEndpoints(),
        OGA1dNormalized(),
        options,
    )


def ShallowNetReversible(
    basis: ShallowNetBasis, quadrature: AbstractQuadrature, **options: Any
) -> NetworkVI:
    """Free endpoints with mirrored neuron pairs `(w, β)`, `(−w, w + β)`, each neuron with its
    own output weight (`MirrorPairs`); the equations are the exact gradient of the action on
    this family, which is closed under reversal of the step. The width must be even."""
    basis = _shallow("ShallowNetReversible", basis, MirrorPairs())
    return _build("ShallowNetReversible", basis, quadrature, FreeEndpoints(), OGA1d(), options)


def ShallowNetAutodiffReversible(
    basis: ShallowNetBasis,
    quadrature: AbstractQuadrature,
    *,
    shared_output_weights: bool = False,
    **options: Any,
) -> NetworkVI:
    """Interpolating endpoints with mirrored neuron pairs `(w, β)`, `(−w, w + β)`; the width
    must be even. The equations are the exact gradient of the action on this family, and the
    family is closed under reversal of the step, so the method is time-symmetric.

    With `shared_output_weights=True` both neurons of a pair share one output weight, in the
    Newton solve itself (the reference shares it only in its seed; `SharedMirrorPairs`). Then
    the network term `τ(1−τ) N(τ)` is symmetric about `τ = 1/2`, the part of the motion that is
    antisymmetric about the step's midpoint can only come from the chord, and the method is
    of order 4 whatever the width. The default, `False`, gives each neuron its own output
    weight (`MirrorPairs`), as the reference's solve does, and keeps full accuracy.
    Seeded by `OGA1d()` with the same symmetry.
    """
    symmetry = SharedMirrorPairs() if shared_output_weights else MirrorPairs()
    basis = _shallow("ShallowNetAutodiffReversible", basis, symmetry)
    return _build(
        "ShallowNetAutodiffReversible",
        basis,
        quadrature,
        InterpolatingEndpoints(),
        OGA1d(),
        options,
    )


def DenseNet(basis: DenseNetBasis, quadrature: AbstractQuadrature, **options: Any) -> NetworkVI:
    """Two-hidden-layer network (`DenseNetBasis`) with free endpoints, seeded by `LSGD()`
    (least squares for the output layer, gradient steps for the hidden ones) or
    `TrainingMethod()` (Adam, via optax)."""
    if not isinstance(basis, DenseNetBasis):
        raise TypeError(f"DenseNet needs a DenseNetBasis, got {basis!r}")
    return _build("DenseNet", basis, quadrature, FreeEndpoints(), LSGD(), options)


def VISE(basis: AbstractBasis, quadrature: AbstractQuadrature, init_w, **options: Any) -> NetworkVI:
    """Variational integrator with a symbolic ansatz in absolute time (`SymbolicAnsatz`), free
    endpoints. The weights start from `init_w` on the first step and from the previous
    step's converged weights afterwards, restarting from `init_w` when they drift more than
    1 from it (`InitialWeights`, the reference's rule); `p_{n+1}` is seeded by the initial
    trajectory's momentum.

    A few weights on a long step can leave the frequency poorly determined, and then the
    restart rule is not enough. On the reference's Hénon–Heiles setting (`h = 2`, `T = 100`,
    `W₁ cos(W₂ t + W₃) + W₄` per coordinate) this configuration converges on every step
    (a test checks it):

        VISE(basis, GaussLegendre(8), init_w,
             initial_guess_method=TrajectoryFit(init_w, iterations=60),
             root_finder=RegularisedNewton(lam=1e-12, patience=100),
             root_find_max_steps=200)

    `TrajectoryFit` fits the weights to the initial trajectory from both the initial and
    the previous weights and keeps the better fit.
    """
    guess = options.pop("initial_guess_method", None) or InitialWeights(init_w)
    return _build("VISE", basis, quadrature, FreeEndpoints(), guess, options)


def CGVI(
    degree: int,
    quadrature: AbstractQuadrature | None = None,
    *,
    points: str = "lobatto",
    **options: Any,
) -> NetworkVI:
    """Classical continuous-Galerkin variational integrator: a polynomial of `degree` in
    Lagrange form (`LagrangeBasis`), free endpoints, Gauss–Legendre with `degree + 1` nodes
    by default (order `2·degree`).

    By default the step is solved on the span of the Lagrange basis in coordinates that are
    orthonormal in the quadrature's norm (`VariableProjection()`), from the previous step's
    polynomial continued: a square, well-conditioned system, solved to round-off
    (`ChordIteration(ftol=0, predict=True, picard=True)`). Where the Lagrangian's
    kinetic matrix is constant, that is the Jacobian-free iteration on the forces at the
    nodes (a step it does not converge on fails, for the step-size controller to retry:
    `RetryFailedSteps`); elsewhere the chord iteration with its Jacobian formed once per
    step, where a step it cannot contract on fails the same way (`restart=True` restarts it
    inside the step from the trajectory seed with Newton's updates instead). A seed option
    (`initial_guess_method`, `initial_trajectory_method`, `extrapolation_substep`, ...) or
    a damped root finder
    (`regularization_factor`, `LevenbergMarquardt()`) selects the reference's form instead:
    the values at the points as unknowns (`FreeEndpoints()`), seeded by an exact
    least-squares fit to the trajectory. Both solve the same equations for the same
    polynomial. `error_estimate=True` gives `diffrax.PIDController` the step's local error
    (the companion of degree `degree + 1`; see `NetworkVI`)."""
    basis = LagrangeBasis(degree, points)
    quadrature = quadrature if quadrature is not None else GaussLegendre(degree + 1)
    seed_options = (set(options) & _KNOWN) - {"max_iterations"}
    damped = "regularization_factor" in options or isinstance(
        options.get("root_finder"), AbstractDampedNewton
    )
    if seed_options or damped:
        return _build("CGVI", basis, quadrature, FreeEndpoints(), LeastSquaresFit(), options)
    _check_options("CGVI", options)
    kwargs: dict[str, Any] = {k: v for k, v in options.items() if k in _SOLVER_OPTIONS}
    if options.get("max_iterations") is not None:
        kwargs["root_find_max_steps"] = options["max_iterations"]
    kwargs.setdefault("root_finder", ChordIteration(ftol=0.0, predict=True, picard=True))
    return NetworkVI(basis, quadrature, formulation=VariableProjection(), **kwargs)


for _method in (ShallowNet, ShallowNetAutodiff, ShallowNetReversible, ShallowNetAutodiffReversible):
    _method.__doc__ = (_method.__doc__ or "") + "\n" + _SHARED_DOC
VISE.__doc__ = (VISE.__doc__ or "") + "\n" + _SHARED_DOC
DenseNet.__doc__ = (DenseNet.__doc__ or "") + "\n" + _SHARED_DOC
CGVI.__doc__ = (CGVI.__doc__ or "") + "\n" + _SHARED_DOC
del _method
