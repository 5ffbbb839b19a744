"""The warning of a network that falls back to the all-parameter step.

`NetworkVI`'s default step for a shallow network is the projected one (`VariableProjection`):
a fixed hidden layer (`UniformLayer`) whose features span enough functions for the
activation, and a square system with an isolated root. For an activation without such a rule
(`UniformLayer.suits`) the default is the reference's all-parameter step, whose roots are not
isolated; `NetworkVI` says so once, when it is built.
"""

from __future__ import annotations

import sys
import warnings
from typing import Any

from ._activations import activation_name

__all__ = ["AllParameterFallbackWarning", "warn_all_parameter_fallback"]


class AllParameterFallbackWarning(UserWarning):
    """A `NetworkVI` left to choose its step got the all-parameter one (`FreeEndpoints()` solved
    by `LevenbergMarquardt()`) because its network's activation has no hidden-layer rule for
    the projected step.

    Raised once per activation and process (a function is the same activation wherever its
    code is written once: a lambda built in a loop warns on the first pass only). Passing
    `formulation=` explicitly, or an option of the all-parameter step (a damped root finder,
    `reuse_neurons`, `PreviousStep()`, a chosen `initial_guess`), chooses the step and does not
    warn; so does `warnings.simplefilter("ignore", AllParameterFallbackWarning)`.
    """


# The activations warned about in this process: a function's code object (the same lambda
# rebuilt is the same activation), else the activation itself.
_WARNED: set[Any] = set()

# Frames of these packages are skipped, so that the warning points at the user's line.
_INTERNAL = frozenset({"diffrax_vi", "equinox", "dataclasses"})


def _key(activation) -> Any:
    key = getattr(activation, "__code__", activation)
    try:
        hash(key)
    except TypeError:
        return ("id", id(activation))
    return key


def _user_stacklevel() -> int:
    """The `stacklevel` of the first frame outside this package (and equinox's and the
    dataclasses' construction code), counted from the caller of this function."""
    frame = sys._getframe(1)
    level = 1
    while frame is not None and frame.f_globals.get("__name__", "").split(".")[0] in _INTERNAL:
        frame = frame.f_back
        level += 1
    return level if frame is not None else 1


def warn_all_parameter_fallback(basis) -> None:
    """Warn (once per activation and process) that `basis`, a network whose activation has no
    hidden-layer rule, gets the all-parameter step by default."""
    key = _key(basis.activation)
    if key in _WARNED:
        return
    _WARNED.add(key)
    name = activation_name(basis.activation)
    warnings.warn(
        f"NetworkVI({basis!r}) falls back to the all-parameter step, FreeEndpoints() solved by "
        f"LevenbergMarquardt(): the activation {name} has no hidden-layer rule for the "
        "projected step, VariableProjection(). The all-parameter step's roots are not "
        "isolated, so each step's result rests on its seed and the energy drifts over a long "
        "run (L = v^2/2 - q^2/2, 2000 steps of 0.5, tanh: 9e-9 relative and growing linearly, "
        "against 1e-14 projected). The projected step is the default for tanh, sigmoid, gelu, "
        "gelu_exact and relu_k(k >= 2), by those names or JAX's (jnp.tanh, jax.nn.tanh, "
        "jax.nn.sigmoid, jax.nn.gelu). Pass formulation= (e.g. formulation=FreeEndpoints() "
        "for this step) to choose the step explicitly and silence this warning.",
        AllParameterFallbackWarning,
        stacklevel=_user_stacklevel(),
    )
