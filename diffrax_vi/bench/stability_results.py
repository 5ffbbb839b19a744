"""What a stability sweep's rows say: convergence rates and the restated stability target.

The restated target (`stability_target`, `report.stability_target_table`): with our
convergence test, at least the rates `TARGET_RATES` of the cases with `dt ≤ 1` converge, per
precision; every case with a larger step ends either *accurate* (successful, `err_t1 ≤
accuracy_tolerance(dtype)`) or *failed* (a non-successful result), never *wrong* (successful
and not accurate, `outcome`); and those cases run again under `RetryFailedSteps`
(`controller="retry"`) reach `t1`. `convergence_rates` counts the constant-step cases the way
the reference's benchmark does (`REFERENCE_RATES` are its quick run's).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

import numpy as np

from .stability import StabilityCase
from .status import converged

__all__ = [
    "ACCURATE_FRACTION",
    "LARGE_DT",
    "REFERENCE_RATES",
    "TARGET_RATES",
    "accuracy_tolerance",
    "convergence_rates",
    "outcome",
    "stability_target",
]

# The reference's quick run (problems_and_benchmarks §2.6): converged / cases per precision.
REFERENCE_RATES = {"float16": (9, 36), "float32": (29, 36), "float64": (15, 36)}
# The restated target (issue 52): strict convergence rate over the cases with dt <= 1.
TARGET_RATES = {"float64": 0.90, "float32": 0.85, "float16": 0.60}
# A successful case with a larger step is accurate when its final q is within this fraction
# of the motion's size of the reference (or within sqrt(eps), where that is larger).
ACCURATE_FRACTION = 1e-2
# Steps above this are the sweep's "large" ones (the quick grid's dt = 10).
LARGE_DT = 1.0


def _controller(row: dict[str, Any]) -> str:
    """A row's controller (rows of CSVs written before the column: `"constant"`)."""
    return row.get("controller") or "constant"


def accuracy_tolerance(dtype: str) -> float:
    """The largest `err_t1` of an *accurate* case: `ACCURATE_FRACTION` (1 % of the motion's
    size), or `√eps` of `dtype` where that is larger (float16: 3.1 %)."""
    return max(ACCURATE_FRACTION, float(np.finfo(np.dtype(dtype)).eps) ** 0.5)


def outcome(row: dict[str, Any]) -> str:
    """How a case ended, in the target's three classes: `"failed"` (a non-successful result,
    or an exception: the solve said it failed), `"accurate"` (successful, with a finite
    `err_t1` at most `accuracy_tolerance(dtype)`), or `"wrong"` (successful but not
    accurate: a silent failure)."""
    result = row.get("result")
    if result is None:  # an exception, or a row written before the column
        return "failed" if str(row.get("status", "")).startswith("error") else "wrong"
    if result != "successful":
        return "failed"
    err = row.get("err_t1")
    if err is None or not np.isfinite(err) or err > accuracy_tolerance(row["dtype"]):
        return "wrong"
    return "accurate"


def _strict_rows(rows: Iterable[dict[str, Any]], controller: str) -> list[dict[str, Any]]:
    return [r for r in rows if (r.get("acceptance") or "strict") == "strict"
            and _controller(r) == controller]


def stability_target(rows: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """The restated target, measured on the rows of a sweep (our convergence test only).

    **Returns** a dict with

    - `"rates"`: per `(solver, dtype)`, over the constant-step cases with `dt ≤ LARGE_DT`:
      `cases`, `converged`, `wrong` (successful, not accurate), `rate`, `target`
      (`TARGET_RATES`); `retry_cases` (those also run under `RetryFailedSteps`) and
      `retry_rate`, the share converged at constant steps or, where not, at `t1` under
      `RetryFailedSteps` (`None` without such runs); `met`, either rate at the target;
    - `"large"`: per `(solver, dtype)`, over the constant-step cases with `dt > LARGE_DT`:
      the counts of `outcome`s (`accurate`, `failed`, `wrong`) and `cases`;
    - `"retry"`: per `(solver, dtype)`, over the large-step cases under `RetryFailedSteps`:
      `cases`, `reached` (`t1`) and the largest `err_t1` of those that reached it;
    - `"adaptive"`: per controller (`"retry"`, `"pid"`) and `(solver, dtype)`, over the same
      cases: `cases` and the counts of `outcome`s (`accurate`, `failed`, `wrong`);
    - `"pairs"`: one dict per large-step case: its fields, `outcome` and `err_t1` with
      constant steps, and `reached`, `err_t1`, `steps`, `rejected` under `RetryFailedSteps`
      (`None` where that run is not in `rows`);
    - `"met"`: the rates met, no `wrong` case with any controller, and every float64 and
      float32 large-step case at `t1` accurately under `RetryFailedSteps` or `PIDController`
      (float16 is reported, not required); `False` where a part has no cases.
    """
    rows = list(rows)
    constant = _strict_rows(rows, "constant")
    retried = _strict_rows(rows, "retry")
    adaptive = {c: _strict_rows(rows, c) for c in ("retry", "pid")}
    keyed = lambda r: (r["solver"], r["dtype"])  # noqa: E731
    out: dict[str, Any] = {"rates": {}, "large": {}, "retry": {}, "adaptive": {}, "pairs": []}
    for controller, runs in adaptive.items():
        for r in runs:
            g = out["adaptive"].setdefault(controller, {}).setdefault(
                keyed(r), dict(cases=0, accurate=0, failed=0, wrong=0))
            g["cases"] += 1
            g[outcome(r)] += 1
    for r in constant:
        if r["dt"] <= LARGE_DT:
            g = out["rates"].setdefault(keyed(r), dict(cases=0, converged=0, wrong=0))
            g["cases"] += 1
            g["converged"] += converged(r["status"])
            g["wrong"] += outcome(r) == "wrong"
        else:
            g = out["large"].setdefault(keyed(r), dict(cases=0, accurate=0, failed=0, wrong=0))
            g["cases"] += 1
            g[outcome(r)] += 1
    fields = [f.name for f in dataclasses.fields(StabilityCase) if f.name != "controller"]
    case_of = lambda r: tuple(r[f] for f in fields if f != "lam")  # noqa: E731
    small_retried = {case_of(r): r for r in retried if r["dt"] <= LARGE_DT}
    retried = [r for r in retried if r["dt"] > LARGE_DT]
    for key, g in out["rates"].items():
        small = [r for r in constant if r["dt"] <= LARGE_DT and keyed(r) == key]
        g["rate"] = g["converged"] / g["cases"]
        g["target"] = TARGET_RATES[key[1]]
        # converged at constant steps, or (where not) at t1 under RetryFailedSteps
        g["retry_cases"] = sum(case_of(r) in small_retried for r in small)
        g["retry_rate"] = (sum(converged(r["status"]) or _reached(small_retried.get(case_of(r), {}))
                               for r in small) / len(small) if g["retry_cases"] else None)
        g["met"] = g["rate"] >= g["target"] or (
            g["retry_rate"] is not None and g["retry_rate"] >= g["target"])
    by_case = {tuple(r[f] for f in fields if f != "lam"): r for r in retried}
    by_pid = {tuple(r[f] for f in fields if f != "lam"): r for r in adaptive["pid"]}
    for r in retried:
        g = out["retry"].setdefault(keyed(r), dict(cases=0, reached=0, max_err_t1=None))
        g["cases"] += 1
        if _reached(r):
            g["reached"] += 1
            if r.get("err_t1") is not None:
                g["max_err_t1"] = max(g["max_err_t1"] or 0.0, r["err_t1"])
    for r in constant:
        if r["dt"] <= LARGE_DT:
            continue
        twin = by_case.get(tuple(r[f] for f in fields if f != "lam"))
        pid = by_pid.get(tuple(r[f] for f in fields if f != "lam"))
        out["pairs"].append(dict(
            problem=r["problem"], dt=r["dt"], dtype=r["dtype"], activation=r["activation"],
            solver=r["solver"], outcome=outcome(r), result=r.get("result"),
            err_t1=r.get("err_t1"),
            retry_reached=None if twin is None else _reached(twin),
            retry_err_t1=None if twin is None else twin.get("err_t1"),
            retry_steps=None if twin is None else twin.get("steps_done"),
            retry_rejected=None if twin is None else twin.get("rejected"),
            retry_outcome=None if twin is None else outcome(twin),
            pid_outcome=None if pid is None else outcome(pid),
            pid_err_t1=None if pid is None else pid.get("err_t1"),
            pid_steps=None if pid is None else pid.get("steps_done"),
        ))
    required = [p for p in out["pairs"] if p["dtype"] != "float16"]
    recovered = [p for p in required
                 if "accurate" in (p["retry_outcome"], p["pid_outcome"])
                 or (p["pid_outcome"] is None and p["retry_reached"])]
    no_wrong = all(g["wrong"] == 0 for part in ("rates", "large")
                   for g in out[part].values()) and all(
        g["wrong"] == 0 for table in out["adaptive"].values() for g in table.values())
    out["met"] = bool(
        out["rates"] and all(g["met"] for g in out["rates"].values())
        and out["large"] and no_wrong and out["retry"]
        and required and len(recovered) == len(required)
    )
    return out


def _reached(row: dict[str, Any]) -> bool:
    return row.get("reached") in (True, "True", 1)


def convergence_rates(rows: Iterable[dict[str, Any]], by: str = "dtype") -> dict[str, dict]:
    """Per value of `by`: cases, converged (`ok` only), measured (`ok` + `maxiter`), the rate,
    and medians of `ref_err`, `ham_drift`, `iterations` over the measured cases. Only the
    constant-step cases count (the runs under `RetryFailedSteps` are `stability_target`'s)."""
    groups: dict[str, list] = {}
    for r in rows:
        if _controller(r) != "constant":
            continue
        groups.setdefault(str(r[by]), []).append(r)
    out = {}
    for key, rs in sorted(groups.items()):
        measured = [r for r in rs if r["status"] in ("ok", "maxiter")]

        def median(field, measured=measured):
            xs = [r[field] for r in measured if r.get(field) is not None]
            return float(np.median(xs)) if xs else None

        ok = sum(converged(r["status"]) for r in rs)
        out[key] = dict(
            cases=len(rs), converged=ok, rate=ok / len(rs), measured=len(measured),
            ref_err=median("ref_err"), ham_drift=median("ham_drift"),
            iterations=median("iterations"),
        )
    return out
