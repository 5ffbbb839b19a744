"""Failure results of a variational step, and where to find the details of a failed step.

A failed step ends `diffrax.diffeqsolve` with one of these members of `diffrax.RESULTS`: four
for the ways the nonlinear solve of a step can end without a root, one for a step that cannot
be taken at all, one for a converged all-parameter network step whose end state has drifted
off the primary constraint of a Lagrangian linear in the velocities (by more than `eps ** 0.5`
relative to `1 + max(|q_n|, |p_n|)`, and 100 times as far as at the run's first step; see
`diffrax_vi._step.degenerate`), one for a step that cannot meet the term's holonomic constraints
(`diffrax_vi._step.holonomic`), one for a converged step of a conserved energy whose energy jumped
far past the method's error (a wrong root of the step's equations; `NetworkVI.energy_check`):

| member | `failure_kind` | meaning |
|---|---|---|
| `RESULTS.vi_step_max_iterations` | `"maxiter"` | the iteration cap `root_find_max_steps` was hit |
| `RESULTS.vi_step_stalled` | `"stalled"` | the residual stopped falling above the tolerance |
| `RESULTS.vi_step_nonfinite` | `"nonfinite"` | NaN or inf in the residual or in the end state |
| `RESULTS.vi_step_singular` | `"singular"` | the linear solve of an iteration broke down |
| `RESULTS.vi_step_size_invalid` | `"step_size"` | the step is zero or not finite (a zero `dt0`) |
| `RESULTS.vi_constraint_drift` | `"constraint_drift"` | end state off `p = ϑ(q)` (first order) |
| `RESULTS.vi_constraint_unmet` | `"constraint_unmet"` | holonomic constraint `g = 0` not met |
| `RESULTS.vi_step_energy_jump` | `"energy_jump"` | converged, but the energy jumped: a wrong root |

diffrax's own failures have kinds too (`"max_steps"`, `"max_rejected"`, `"dt_min"`), and so do
the results of optimistix and lineax (a divergent root find is `"diverged"`); see `FAILURE_KINDS`.

`diffrax.diffeqsolve` only forwards members of its own `RESULTS`, and only checks results with
`is_okay`, so the members are registered on `diffrax.RESULTS` itself when `diffrax_vi` is
imported (equinox enumerations are append-only tables of static messages). With `throw=True`
the solve raises with the member's message; with `throw=False` `sol.result` is the member, the
steps before the failed one are kept, and the failed step's end state is NaN (it is never
passed off as a result).

Equinox messages are static strings, so the time and the residual of the failed step cannot be
part of them. They are in the solver state instead: `SaveAt(..., solver_state=True)`, then
`sol.solver_state.report` (a `StepReport`), or `describe_failure(sol)` for one readable line.
With constant steps the report is that of the failed step; an adaptive controller rejects a
failed step (its error estimate is infinite) and throws its state away, so the report is then
that of the last accepted step. `RetryFailedSteps` throws away the failed trials it retries,
and keeps the one that ends the run (a piece of the smallest length that still fails), so
its report is that of the failed piece.
"""

from __future__ import annotations

from typing import Any

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx

# The one deliberate use of equinox's private enumeration tables: equinox has no public way
# to add a member to an enumeration (`_register`) or to read a member's name and index
# (`result_names`); every other module goes through these two functions.
from equinox import _enum
from jaxtyping import Array

__all__ = [
    "StepReport", "failure_kind", "describe_failure", "from_root_find", "result_names",
    "STEP_FAILURES",
]

_WHERE = (
    " The start time, length and residual of the failed step are in the solver state: "
    "pass saveat=diffrax.SaveAt(..., solver_state=True) and throw=False, then read "
    "sol.solver_state.report or call diffrax_vi.describe_failure(sol)."
)

_MESSAGES = {
    "vi_step_max_iterations": (
        "diffrax_vi: the nonlinear solve of a step reached root_find_max_steps without "
        "converging. Try a smaller step, a larger root_find_max_steps or a better seed, or "
        "stepsize_controller=diffrax_vi.RetryFailedSteps() to retry such steps in pieces."
        + _WHERE
    ),
    "vi_step_stalled": (
        "diffrax_vi: the nonlinear solve of a step stalled: its residual stopped falling "
        "above the tolerance (no root near the seed). Try a smaller step or another seed, or "
        "stepsize_controller=diffrax_vi.RetryFailedSteps() to retry such steps in pieces."
        + _WHERE
    ),
    "vi_step_nonfinite": (
        "diffrax_vi: a step produced NaN or inf (in the residual of its nonlinear solve or "
        "in its end state). Check the Lagrangian at the current state, or reduce the step." + _WHERE
    ),
    "vi_step_singular": (
        "diffrax_vi: the linear solve inside a step's nonlinear solve broke down (singular "
        "Jacobian). Use LevenbergMarquardt() or a larger regularisation lam." + _WHERE
    ),
    "vi_step_size_invalid": (
        "diffrax_vi: the step size must be finite and non-zero (check dt0, t0 and t1: a zero "
        "dt0 gives such a step)." + _WHERE
    ),
    "vi_constraint_drift": (
        "diffrax_vi: an all-parameter network step of a Lagrangian linear in the velocities "
        "converged to an end state drifting off its primary constraint p = dL/dv(q) (by more "
        "than sqrt(eps) relative to 1 + max(|q|, |p|), and 100 times as far as at the first "
        "step): its roots are not isolated and its accuracy is lost. Use the projected step "
        "(formulation=None or VariableProjection()) or a polynomial CGVI." + _WHERE
    ),
    "vi_constraint_unmet": (
        "diffrax_vi: a holonomic constraint g(t, q) = 0 of the term, or its hidden velocity "
        "constraint G(q) v + dg/dt = 0, could not be met (by sqrt(eps) relative to the "
        "state's size): the step's start is off them (start on both: project the initial "
        "state), or the step's solve cannot reach them (a smaller step, or constraints with "
        "independent gradients). The largest drift so far is in "
        "sol.solver_state.holonomic_drift." + _WHERE
    ),
    "vi_step_energy_jump": (
        "diffrax_vi: the nonlinear solve of a step converged, but the energy of its end state "
        "differs from that of its start by more than the method's error allows (a conserved "
        "energy: the solve found a wrong root of the step's equations, as it can at steps "
        "near the motion's time scale). Take smaller steps, or "
        "stepsize_controller=diffrax_vi.RetryFailedSteps() to retry such steps in pieces "
        "(energy_check=False turns the check off)." + _WHERE
    ),
}


def _register(enumeration, name: str, message: str):
    # `Enumeration` classes keep their members in two class-level tables filled by the
    # metaclass; a subclass of `diffrax.RESULTS` would not survive `diffeqsolve` (it only
    # `where`s members of its own class), so the members are added to `diffrax.RESULTS`.
    # Re-registering the same name keeps its index, so a module reload is harmless.
    _enum._store(
        enumeration, name, message, enumeration._name_to_item, enumeration._index_to_message
    )
    return getattr(enumeration, name)


# The largest energy change of a step, relative to the energy's scale at its start, that
# counts as the method's error: above it `diffrax_vi._step.energy_check` fails the step with
# `vi_step_energy_jump` (docs/benchmarks.md, "Energy check", has the measurements it was
# chosen from).
JUMP_TOLERANCE = 0.5

STEP_FAILURES = {name: _register(diffrax.RESULTS, name, msg) for name, msg in _MESSAGES.items()}
# Member name -> failure kind: one kind per way of failing, so that a kind says what happened.
FAILURE_KINDS = {
    "vi_step_max_iterations": "maxiter",
    "vi_step_stalled": "stalled",
    "vi_step_nonfinite": "nonfinite",
    "vi_step_singular": "singular",
    "vi_step_size_invalid": "step_size",
    "vi_constraint_drift": "constraint_drift",
    "vi_constraint_unmet": "constraint_unmet",
    "vi_step_energy_jump": "energy_jump",
    # diffrax's own failures: the step budget, the step size controller.
    "max_steps_reached": "max_steps",
    "max_steps_rejected": "max_rejected",
    "dt_min_reached": "dt_min",
    # The same failures as reported by optimistix/lineax (other root finders, other solvers).
    "nonlinear_max_steps_reached": "maxiter",
    "nonlinear_divergence": "diverged",
    "nonfinite": "nonfinite",
    "nonfinite_input": "nonfinite",
    "singular": "singular",
    "breakdown": "singular",
    "stagnation": "stalled",
    "conlim": "singular",
}


def from_root_find(result: optx.RESULTS) -> diffrax.RESULTS:
    """The step failure (a `diffrax.RESULTS` member) for the result of a step's root find:
    one lookup in a table over optimistix's results (a chain of comparisons would be one
    instruction each in every compiled step)."""
    value = lookup(_ROOT_FIND_TABLE, result._value)
    return eqx.tree_at(lambda r: r._value, diffrax.RESULTS.successful, value)


def lookup(table: np.ndarray, index) -> Array:
    """`table[index]` for a small constant table and an index known to lie in it: taken as
    unsigned and in bounds, so that neither a wrap of negative indices nor clamping is
    compiled."""
    index = jnp.asarray(index).astype(jnp.uint32)
    return jnp.asarray(table).at[index].get(mode="promise_in_bounds")


def _root_find_table() -> np.ndarray:
    """`table[i]`: the index of the `diffrax.RESULTS` member for optimistix's result `i`."""
    names = dict((
        ("nonlinear_max_steps_reached", "vi_step_max_iterations"),
        ("nonlinear_divergence", "vi_step_stalled"),
        ("stagnation", "vi_step_stalled"),
        ("nonfinite", "vi_step_nonfinite"),
        ("nonfinite_input", "vi_step_nonfinite"),
    ))
    table = np.full(len(optx.RESULTS), int(STEP_FAILURES["vi_step_singular"]._value), np.int32)
    for name, item in optx.RESULTS._name_to_item.items():
        index = int(item._value)
        if name == "successful":
            table[index] = int(diffrax.RESULTS.successful._value)
        elif name in names:
            table[index] = int(STEP_FAILURES[names[name]]._value)
    return table


_ROOT_FIND_TABLE = _root_find_table()


def failure_kind(result) -> str | np.ndarray:
    """Classify a result by what went wrong, one kind per way of failing.

    `"ok"` (`successful`, `event_occurred`); for a step's nonlinear solve `"maxiter"`,
    `"stalled"`, `"nonfinite"`, `"singular"`, and `"diverged"` (optimistix's divergence);
    `"step_size"` (a zero or non-finite step); `"constraint_drift"` (a first-order
    Lagrangian's step off its primary constraint); `"constraint_unmet"` (a holonomic
    constraint not met); `"energy_jump"` (a converged step whose conserved energy jumped: a
    wrong root); diffrax's `"max_steps"` (the step budget ran
    out), `"max_rejected"` and `"dt_min"` (adaptive steps); `"other"` for anything else.

    Accepts a `diffrax.RESULTS` or `optimistix.RESULTS` member (e.g. `sol.result`), concrete,
    not traced. A batched result (from `vmap`) gives an array of kinds of the same shape.
    """
    enumeration = getattr(result, "_enumeration", None)
    if enumeration is None or not issubclass(enumeration, optx.RESULTS):
        raise TypeError(
            f"failure_kind takes a diffrax or optimistix RESULTS member, got {result!r}"
        )
    if result.is_traced():
        raise ValueError("failure_kind needs a concrete result (call it outside jit)")

    def kind(name: str) -> str:
        if name in ("successful", "event_occurred"):
            return "ok"
        return FAILURE_KINDS.get(name, "other")

    names = result_names(result)
    if names.ndim == 0:
        return kind(str(names))
    return np.vectorize(kind, otypes=[object])(names).astype(str)


def result_names(result: Any) -> np.ndarray:
    """The member names of a concrete `RESULTS` item (diffrax, optimistix, lineax): a string
    array of the item's shape (a 0-d array for one solve)."""
    enumeration = getattr(result, "_enumeration", None)
    table = getattr(enumeration, "_name_to_item", None)
    if table is None:
        raise TypeError(f"expected a diffrax/optimistix/lineax RESULTS member, got {result!r}")
    names = {int(np.asarray(item._value)): name for name, item in table.items()}
    value = np.asarray(result._value)
    unknown = set(np.unique(value).tolist()) - set(names)
    if unknown:
        raise ValueError(f"unknown result index {sorted(unknown)} of {enumeration.__name__}")
    return np.vectorize(names.__getitem__, otypes=[object])(value).astype(str)


class StepReport(eqx.Module):
    """How the nonlinear solve of the most recent step ended (`NetworkVIState.report`).

    - `t`, `h`: start time and length of the step (in the direction of integration).
    - `residual`: `max|F|` of the step's equations where its solve stopped.
    - `tolerance`: the residual the solve counted as converged (`ftol·scale`; NaN for root
      finders that are not `diffrax_vi`'s own).
    - `iterations`: nonlinear iterations of the step.
    - `result`: `diffrax.RESULTS.successful` or one of the step failures.
    - `constraint`: for a Lagrangian linear in the velocities, `max|p_{n+1} − ϑ(q_{n+1})|`
      relative to `1 + max(|q_n|, |p_n|)`; 0 for any other Lagrangian. Above `sqrt(eps)`
      and 100 times its value at the run's first step, the all-parameter step of a network
      fails (`RESULTS.vi_constraint_drift`); for the other steps, whose roots are isolated,
      it is the step's truncation error.
    - `energy_jump`: where the energy check applies (`NetworkVI.energy_check`), the step's
      `|H₁ − H₀|` relative to its start's energy scale `|p₀·v₀| + |L₀|`; 0 where it does
      not. Above `diffrax_vi._step.energy_check.JUMP_TOLERANCE` the step fails
      (`RESULTS.vi_step_energy_jump`).
    """

    t: Array
    h: Array
    residual: Array
    tolerance: Array
    iterations: Array
    result: diffrax.RESULTS
    constraint: Array
    energy_jump: Array


def describe_failure(sol: diffrax.Solution) -> str | None:
    """One line on a failed solve of `NetworkVI`, or `None` if it succeeded.

    Names the kind of failure and where it happened, read from `sol.solver_state.report`
    (the solve needs `SaveAt(..., solver_state=True)`; without it the line says so):

    - a failed step: its interval, the residual where its solve stopped and the tolerance;
    - a step that converged to a wrong root (`"energy_jump"`): its interval and its energy
      change relative to the energy's scale at its start;
    - a step that could not start because its start state is not finite (at `t0`: `y0` has a
      NaN or inf): says so, instead of blaming the Lagrangian or the step. This is read from
      the tolerance of `diffrax_vi`'s root finders, which scales with the start state; an
      optimistix root finder reports none, so there the line adds that a Lagrangian that is
      NaN at the start state looks the same;
    - diffrax's step budget (`max_steps`) or step size controller: how far the solve got
      (the end of the last accepted step) and what to change.
    """
    kind = failure_kind(sol.result)
    if isinstance(kind, np.ndarray):
        raise ValueError("describe_failure takes one solve, not a batch; index it first")
    if kind == "ok":
        return None
    message = diffrax.RESULTS[sol.result].split(_WHERE)[0]
    report = getattr(sol.solver_state, "report", None)
    if not isinstance(report, StepReport):
        return f"{kind}: {message} (no step report: solve with SaveAt(solver_state=True))"
    t, h = float(report.t), float(report.h)
    residual, tolerance = float(report.residual), float(report.tolerance)
    iterations = int(report.iterations)
    step = f"[{t:.6g}, {t + h:.6g}] (h = {h:.3g})"
    if failure_kind(report.result) == "ok":
        # Not a failed step: diffrax stopped the loop (step budget, step size controller), or
        # an adaptive controller rejected the failed step and kept the last accepted one.
        reached = t + h
        t1 = float(np.asarray(sol.t1))
        if kind in ("max_steps", "max_rejected"):
            budget = sol.stats.get("max_steps") if isinstance(sol.stats, dict) else None
            spent = f"all {int(budget)} steps of max_steps" if budget is not None else "max_steps"
            return (
                f"{kind}: the step budget ran out: {spent} were used and the solve stopped at "
                f"t = {reached:.6g}, short of t1 = {t1:.6g} (the last step, {step}, converged). "
                "Pass a larger max_steps to diffeqsolve, or take larger steps."
            )
        return (
            f"{kind}: the solve stopped at t = {reached:.6g}, short of t1 = {t1:.6g}; the last "
            f"accepted step was {step} (residual {residual:.3e}). {message}"
        )
    if kind == "nonfinite" and iterations == 0 and not np.isfinite(tolerance) and (
        np.isinf(tolerance) or np.isnan(residual)
    ):
        # The tolerance of diffrax_vi's root finders is ftol·(1 + max(|q|, |p|)) at the start
        # of the step: it is finite exactly when the start state is.
        # An optimistix root finder reports no tolerance (NaN) at all: there a NaN residual
        # before the first iteration may also be a Lagrangian that is NaN at a finite state.
        start = "the initial state y0" if t == float(np.asarray(sol.t0)) else "its start state"
        caveat = (
            ""
            if np.isinf(tolerance)
            else " (With an optimistix root finder, which reports no tolerance, a Lagrangian "
            "that is NaN at the start state looks the same.)"
        )
        return (
            f"{kind}: the step {step} could not start: {start} (q, p) is not finite (NaN or "
            f"inf). Check y0 = (q, p); the Lagrangian and the step are not at fault.{caveat}"
        )
    if kind == "constraint_drift":
        constraint = float(report.constraint)
        return (
            f"{kind}: step {step} converged (residual {residual:.3e}, {iterations} iterations) "
            f"to an end state {constraint:.3e} (relative) off the primary constraint "
            f"p = dL/dv(q). {message}"
        )
    if kind == "energy_jump":
        return (
            f"{kind}: step {step} converged (residual {residual:.3e}, {iterations} iterations) "
            f"but its energy changed by {float(report.energy_jump):.3e} times the energy's "
            f"scale at its start (|p·v| + |L|; at most "
            f"{_energy_jump_tolerance():g} is the method's error). {message}"
        )
    bound = (
        f"tolerance {tolerance:.3e}"
        if np.isfinite(tolerance)
        else "no tolerance reported by this root finder"
    )
    return (
        f"{kind}: step {step} stopped at residual {residual:.3e} ({bound}) after "
        f"{iterations} iterations. {message}"
    )


def _energy_jump_tolerance() -> float:
    return JUMP_TOLERANCE
