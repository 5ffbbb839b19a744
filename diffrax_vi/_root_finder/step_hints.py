"""The interface between `NetworkVI` and its root finder: what the solver knows about a
step's equations beyond the residual function and the start.

optimistix hands a root finder the caller's `options` dictionary untouched; `NetworkVI`
puts one `StepHints` there, under the key `"step"`. A root finder that reads it derives from
`AbstractStepRootFinder` and names the hints it uses in `hints_read`; it then gets every
feature of the step that depends on them. Any other optimistix root finder still solves the
step, without them (`missing_hints` says which, and the solver warns when it is given one).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

__all__ = [
    "HINT_FEATURES",
    "AbstractStepRootFinder",
    "StepHints",
    "StepRootFinderTraits",
    "hints_of",
    "missing_hints",
    "step_options",
    "traits_of",
]

OPTIONS_KEY = "step"


class StepHints(eqx.Module):
    """What the solver tells its root finder about one step's system `F(y, args) = 0`.

    - `scale`: the size of the residual's terms, `1 + max(|q_n|, |p_n|)`; tolerances are
      relative to it.
    - `outputs`: `y ↦` the step's results (`(q_{n+1}, p_{n+1})`): a solve may end where the
      residual stopped falling but these no longer change.
    - `jacobian`: `(y, args) ↦` the dense Jacobian of `F`, assembled by the formulation.
    - `inverse`: `(jacobian, y, args) ↦` the inverse of the Jacobian formed at `y`,
      computed the formulation's own cheaper way (possibly non-finite where that way fails:
      check). It takes the Jacobian the root finder formed (by the hint `jacobian` or
      `jax.jacfwd`), so that a fallback factorisation of the same matrix does not form it
      again.
    - `kinetic`: `(y, args) ↦` the inverse of the kinetic part of the Jacobian (the projected
      step), for a fixed-point iteration.
    - `max_iterations`: the solver's iteration cap. A root finder that reads it may run the
      whole solve in one optimistix step (its own loop, without optimistix's bookkeeping on
      every iteration) and count its iterations in its state's `iterations`.
    - `restart`: `(first_try, start)`: a solve not converged after `first_try` iterations
      starts once more from `start(args)` (with `max_iterations`).
    - `update`: `(y, F, args) ↦` an update of the unknowns by a constant matrix, for the
      Jacobian-free iteration (`JacobianFreeIteration`): the step offers it where its
      Jacobian is constant but for slowly changing terms.
    - `fast_residual`: `(y, args) ↦` the residual and its aux as `fn` gives them, evaluated
      a cheaper way that has no derivatives (for an iteration that needs none).
    - `fallback`: `args ↦` a second starting point (a fresh seed fit), where a solve from the
      given start fails; `fallback_usable(args)` says whether it may be used, and
      `start_at_fallback(args)` makes the solve begin there instead.

    Every hint is optional (`None`, or a `scale` of 1): a root finder must work without it.
    """

    scale: Any = 1.0
    outputs: Callable | None = None
    jacobian: Callable | None = None
    inverse: Callable | None = None
    kinetic: Callable | None = None
    max_iterations: int | None = None
    restart: tuple | None = None
    update: Callable | None = None
    fast_residual: Callable | None = None
    fallback: Callable | None = None
    fallback_usable: Callable | None = None
    start_at_fallback: Callable | None = None


# What a root finder that does not read a hint goes without, for `missing_hints` and the
# solver's warning.
HINT_FEATURES = {
    "scale": "tolerances relative to the size of the state (it stops on its own tolerances)",
    "outputs": "ending a solve whose residual sits at the rounding floor of a rank-deficient "
    "system once the step's results have settled",
    "jacobian": "the Jacobian assembled in closed form by the formulation",
    "fallback": "a restart from a fresh seed fit where the solve from a carried seed fails",
}


def step_options(hints: StepHints) -> dict[str, StepHints]:
    """The `options` of `optimistix.root_find` that carry `hints`."""
    return {OPTIONS_KEY: hints}


def hints_of(options: dict | None) -> StepHints:
    """The hints in a root finder's `options` (empty hints where the caller gave none)."""
    hints = (options or {}).get(OPTIONS_KEY)
    return StepHints() if hints is None else hints


class StepRootFinderTraits(eqx.Module):
    """What the step asks of its root finder beyond optimistix's interface, with the answers
    for a root finder that knows nothing of the step (any optimistix root finder, through
    `traits_of`). `AbstractStepRootFinder` derives from it and its subclasses answer for
    themselves."""

    hints_read: ClassVar[frozenset[str]] = frozenset()

    def reads_hint(self, name: str) -> bool:
        """Whether it uses the hint `name` of `StepHints`."""
        return name in self.hints_read

    def was_restarted(self, state: Any) -> Array:
        """Whether the solve that ended in `state` restarted from a second start."""
        del state
        return jnp.array(False)

    def final_residual(self, state: Any, dtype) -> tuple[Array, float] | None:
        """`(flat residual, ftol)` where the solve ended, read off its final `state`, with the
        residual it had to reach relative to the hint `scale`; `None` where the state does
        not keep them (the caller evaluates the residual)."""
        del state, dtype
        return None

    def jacobian_mode(self) -> str | None:
        """How it wants the Jacobian: `"structured"` (the formulation's block assembly),
        `"auto"` (that where it has a closed form), another mode of its own, or `None`."""
        return None

    def companion(self) -> optx.AbstractRootFinder | None:
        """The root finder of the error estimate's companion step (all the coefficients of a
        polynomial); `None`: this one."""
        return None

    def allows_picard(self) -> bool:
        """Whether the projected step may take the Jacobian-free iteration
        (`diffrax_vi._step.jacobian_free`) in its place."""
        return False

    def picard_falls_back(self) -> bool:
        """Whether a step the Jacobian-free iteration does not converge on goes on with
        Newton's iteration (else it fails, for the step-size controller to retry)."""
        return False


class AbstractStepRootFinder(optx.AbstractRootFinder, StepRootFinderTraits):
    """An optimistix root finder that reads the solver's `StepHints` (`hints_of(options)`).
    `hints_read` names the hints it uses; the methods of `StepRootFinderTraits` say the rest
    of what the step needs to know of it."""


_NO_TRAITS = StepRootFinderTraits()


def traits_of(root_finder: optx.AbstractRootFinder) -> StepRootFinderTraits:
    """The step's questions answered for `root_finder`: by itself where it derives from
    `AbstractStepRootFinder`, else the answers for a root finder that reads no hint."""
    return root_finder if isinstance(root_finder, AbstractStepRootFinder) else _NO_TRAITS


def missing_hints(root_finder: optx.AbstractRootFinder) -> dict[str, str]:
    """The features of `HINT_FEATURES` that `root_finder` goes without, by hint name."""
    traits = traits_of(root_finder)
    return {name: what for name, what in HINT_FEATURES.items() if not traits.reads_hint(name)}
