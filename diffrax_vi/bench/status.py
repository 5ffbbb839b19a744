"""One place that says how a finished solve ended: `classify`.

Every benchmark in `diffrax_vi.bench` reports a status per run, one of

- `"ok"`: the solve succeeded and its final state is finite;
- `"maxiter"`: a step's nonlinear solve hit its iteration cap (finite, but not converged);
- `"singular"`: a linear solve inside a step broke down;
- `"diverged"`: a step's nonlinear solve gave up (stalled residual, no root near the seed), or
  an adaptive integrator failed (step size underflow);
- `"nonfinite"`: NaN or inf in the result, whatever the solver said;
- `"error:<name>"`: anything else: an exception (`<name>` is its type) or a failure result
  that is none of the above (`<name>` is the `RESULTS` member, e.g. `max_steps_reached` when
  diffrax's own step budget ran out).

The mapping from result members to statuses is the table `RESULT_STATUS`, keyed by member name,
so failure members added to `diffrax.RESULTS` later only need a line there.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._results import FAILURE_KINDS, result_names

__all__ = ["STATUSES", "RESULT_STATUS", "classify", "result_name", "converged"]

STATUSES = ("ok", "maxiter", "singular", "diverged", "nonfinite")

# Member name (of diffrax/optimistix/lineax RESULTS) -> status. The failures of a step's solve
# share their names with `diffrax_vi._results`; members not listed are reported as
# `error:<name>`.
RESULT_STATUS: dict[str, str] = {
    "successful": "ok",
    "event_occurred": "ok",
    "dt_min_reached": "diverged",  # an adaptive step size collapsed
    # The failure kinds of `failure_kind`, folded into the benchmarks' coarser classes (a stall
    # counts as "diverged", as in the reference's tables); the rest stay `error:<name>`.
    **{
        name: "diverged" if kind == "stalled" else kind
        for name, kind in FAILURE_KINDS.items()
        if kind in STATUSES or kind == "stalled"
    },
}


def result_name(result: Any) -> str:
    """The member name of a concrete (not traced, not batched) `RESULTS` item."""
    names = result_names(result)
    if names.ndim != 0:
        raise ValueError(f"classify one solve at a time; got a batch of results {names.shape}")
    return str(names)


def _all_finite(tree) -> bool:
    import jax

    leaves = jax.tree_util.tree_leaves(tree)
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in leaves)


def _final_state(ys, ts):
    """The last saved state; with `SaveAt(steps=True)` the buffer past the end is padding."""
    import jax

    index = -1
    if ts is not None:
        reached = np.flatnonzero(np.isfinite(np.asarray(ts)))
        if reached.size:
            index = int(reached[-1])
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[index], ys)


def _hit_iteration_cap(state, cap: int | None) -> bool:
    if state is None or cap is None:
        return False
    most = getattr(state, "max_iterations", None)
    if most is None:
        return False
    return bool(np.max(np.asarray(most)) >= cap)


def classify(outcome: Any, *, iteration_cap: int | None = None) -> str:
    """The status of a finished solve (see the module docstring for the classes).

    **Arguments:**

    - `outcome`: a `diffrax.Solution` (run with `throw=False`), a scipy `solve_ivp` result,
      or the exception a run raised.
    - `iteration_cap`: the per-step iteration cap of the solver (`root_find_max_steps`). When
      given and the solution carries a solver state whose `max_iterations` reached it, a
      failed solve is `"maxiter"` whatever its result member says.

    **Returns:** one of `STATUSES` or `"error:<name>"`.
    """
    if isinstance(outcome, BaseException):
        return f"error:{type(outcome).__name__}"
    # scipy.integrate.solve_ivp's OdeResult: status 0 (end reached), -1 (failed), 1 (event)
    if hasattr(outcome, "status") and hasattr(outcome, "y") and hasattr(outcome, "message"):
        if not np.all(np.isfinite(np.asarray(outcome.y))):
            return "nonfinite"
        return "ok" if outcome.status >= 0 else "diverged"
    result = getattr(outcome, "result", None)
    if result is None:
        raise TypeError(
            "classify takes a diffrax.Solution, a scipy solve_ivp result or an exception; got "
            f"{type(outcome).__name__}"
        )
    name = result_name(result)
    status = RESULT_STATUS.get(name)
    if status == "ok":
        ys = getattr(outcome, "ys", None)
        if ys is not None and not _all_finite(_final_state(ys, getattr(outcome, "ts", None))):
            return "nonfinite"
        return "ok"
    if _hit_iteration_cap(getattr(outcome, "solver_state", None), iteration_cap):
        return "maxiter"
    return status if status is not None else f"error:{name}"


def converged(status: str) -> bool:
    """Whether a status counts as converged (only `"ok"`; `"maxiter"` does not)."""
    return status == "ok"
