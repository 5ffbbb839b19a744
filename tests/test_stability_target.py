"""The stability sweep's restated target (issue 52): the strict rates at dt <= 1, the large
steps split into accurate / failed / wrong, and the same cases under `RetryFailedSteps`.
The classification and the tables are checked on hand-made rows (no compilation); one
short run goes through the sweep's retry path."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffrax_vi.bench import read_rows, report, write_rows
from diffrax_vi.bench.stability import SWEEP_COLUMNS, StabilityCase, quick_grid, run_case
from diffrax_vi.bench.stability_results import (
    TARGET_RATES,
    accuracy_tolerance,
    outcome,
    stability_target,
)


def _row(dt, dtype="float64", status="ok", result="successful", err=1e-9, controller="constant",
         problem="pendulum", activation="tanh", **extra):
    case = StabilityCase(problem, dt, dtype, 8, 8, activation, "projection",
                         controller=controller)
    row = dataclasses.asdict(case)
    row.update(lam=0.0, status=status, result=result, err_t1=err, **extra)
    return row


def test_accuracy_tolerance_is_one_percent_or_sqrt_eps():
    assert accuracy_tolerance("float64") == accuracy_tolerance("float32") == 1e-2
    assert accuracy_tolerance("float16") == pytest.approx(np.finfo(np.float16).eps ** 0.5)


def test_outcome_has_three_classes():
    assert outcome(_row(10.0, err=5e-3)) == "accurate"
    assert outcome(_row(10.0, dtype="float16", err=3e-2)) == "accurate"  # under sqrt(eps)
    assert outcome(_row(10.0, err=2e-2)) == "wrong"
    assert outcome(_row(10.0, err=None, status="nonfinite")) == "wrong"  # NaN, "successful"
    assert outcome(_row(10.0, err=float("inf"))) == "wrong"
    assert outcome(_row(10.0, status="diverged", result="vi_step_stalled", err=None)) == "failed"
    assert outcome(_row(10.0, status="maxiter", result="vi_step_max_iterations")) == "failed"
    exception = _row(10.0, status="error:ValueError", result=None, err=None)
    assert outcome(exception) == "failed"


def _tiny_sweep():
    """Float64: 2 of 2 small-step cases converge; float32: 1 of 2 (under its 85 %); float16
    none measured at dt <= 1. The large steps: one of each class, and their retries."""
    return [
        _row(0.1), _row(1.0),
        _row(0.1, dtype="float32"),
        _row(1.0, dtype="float32", status="diverged", result="vi_step_stalled", err=None),
        _row(10.0, err=5e-3),  # accurate
        _row(10.0, activation="gelu", status="diverged", result="vi_step_stalled", err=None),
        _row(10.0, dtype="float32", err=0.5),  # wrong
        _row(10.0, controller="retry", err=4e-3, reached=True, steps_done=10, rejected=0),
        _row(10.0, activation="gelu", controller="retry", err=2e-3, reached=True,
             steps_done=14, rejected=4),
        _row(10.0, dtype="float32", controller="retry", err=None, reached=False,
             result="vi_step_stalled", status="diverged", steps_done=3, rejected=8),
        # the reference's accounting is not the target's
        dict(_row(1.0, status="diverged", result="vi_step_stalled"), acceptance="reference"),
    ]


def test_stability_target_counts_each_part():
    t = stability_target(_tiny_sweep())
    f64, f32 = t["rates"][("projection", "float64")], t["rates"][("projection", "float32")]
    assert (f64["cases"], f64["converged"], f64["met"]) == (2, 2, True)
    assert (f32["cases"], f32["converged"], f32["rate"], f32["met"]) == (2, 1, 0.5, False)
    assert f32["target"] == TARGET_RATES["float32"] == 0.85
    assert t["large"][("projection", "float64")] == dict(cases=2, accurate=1, failed=1, wrong=0)
    assert t["large"][("projection", "float32")] == dict(cases=1, accurate=0, failed=0, wrong=1)
    assert t["retry"][("projection", "float64")] == dict(cases=2, reached=2, max_err_t1=4e-3)
    assert t["retry"][("projection", "float32")] == dict(cases=1, reached=0, max_err_t1=None)
    pairs = {(p["dtype"], p["activation"]): p for p in t["pairs"]}
    assert len(pairs) == 3
    gelu = pairs[("float64", "gelu")]
    assert gelu["outcome"] == "failed" and gelu["retry_reached"] is True
    assert (gelu["retry_err_t1"], gelu["retry_steps"], gelu["retry_rejected"]) == (2e-3, 14, 4)
    assert pairs[("float32", "tanh")]["retry_reached"] is False
    assert t["met"] is False
    # without the float32 cases every part holds
    rows = [r for r in _tiny_sweep() if r["dtype"] == "float64"]
    assert stability_target(rows)["met"] is True
    # a float16 retry that fails is reported, not required
    f16 = _row(10.0, dtype="float16", controller="retry", err=None, reached=False,
               result="vi_step_stalled")
    assert stability_target([*rows, f16])["met"] is True
    # under PIDController: counted per outcome; a wrong success anywhere fails the target,
    # and a case recovered accurately by either controller counts as recovered
    pid = _row(10.0, controller="pid", err=3e-3, reached=True, steps_done=40, rejected=3)
    with_pid = stability_target([*rows, pid])
    assert with_pid["adaptive"]["pid"][("projection", "float64")] == dict(
        cases=1, accurate=1, failed=0, wrong=0)
    assert {p["pid_outcome"] for p in with_pid["pairs"]} == {"accurate", None}
    assert with_pid["met"] is True
    wrong_pid = dict(pid, err_t1=0.5)
    assert stability_target([*rows, wrong_pid])["met"] is False
    # a rate under its target at constant steps is met where the same cases under
    # RetryFailedSteps end accurately at t1 at the target's rate
    slow = dict(_row(1.0), status="diverged", result="vi_step_stalled", err_t1=None)
    retried = _row(1.0, controller="retry", err=2e-9, reached=True, steps_done=12, rejected=2)
    missed = stability_target([r for r in rows if r["dt"] != 1.0] + [slow])
    assert missed["rates"][("projection", "float64")]["met"] is False
    recovered = stability_target([r for r in rows if r["dt"] != 1.0] + [slow, retried])
    g = recovered["rates"][("projection", "float64")]
    assert (g["rate"], g["retry_cases"], g["retry_rate"], g["met"]) == (0.5, 1, 1.0, True)
    assert recovered["met"] is True
    # a wrong success at a small step fails the target too
    assert stability_target([*rows, _row(0.1, err=0.5)])["met"] is False
    # a large step without its retry run: the pair says so, and the target is not met
    lone = stability_target([r for r in rows if r["controller"] == "constant"])
    assert {p["retry_reached"] for p in lone["pairs"]} == {None} and lone["met"] is False


def test_target_table_and_csv_round_trip(tmp_path):
    path = tmp_path / "stability.csv"
    write_rows(_tiny_sweep(), path, columns=SWEEP_COLUMNS)
    rows = read_rows(path)  # booleans come back as text, numbers as numbers
    assert stability_target(rows) == stability_target(_tiny_sweep())
    text = report.stability_table(rows)
    assert text.startswith("Restated target")
    assert ("| projection | float32 | 1/2 (50 %) | – | 0 | 85 % | **no** | 0 / 0 / 1 | 0/1 | – "
            "| 0 / 1 / 0 | – |") in text
    assert ("| projection | float64 | 2/2 (100 %) | – | 0 | 90 % | yes | 1 / 1 / 0 | 2/2 "
            "| 4.00e-03 | 2 / 0 / 0 | – |") in text
    assert "Target **not met**" in text and "**wrong**" in text
    # the reference's tables below count the constant-step cases only
    assert "| float64 | ours | 4 | 3 | 75 % |" in text
    # rows of a CSV written before the target's columns: the old tables only
    constant = [r for r in rows if r["controller"] == "constant"]
    assert "Target not checked: no runs under" in report.stability_target_table(constant)
    old = [{k: v for k, v in r.items() if k not in ("result", "controller")} for r in constant]
    assert not report.stability_table(old).startswith("Restated target")


def test_quick_grid_adds_the_large_steps_under_retry():
    cases = quick_grid(solvers=("projection",))
    retry = [c for c in cases if c.controller == "retry"]
    pid = [c for c in cases if c.controller == "pid"]
    assert len(cases) == 54 + 36 + 18 and (len(retry), len(pid)) == (36, 18)
    assert {c.dt for c in retry} == {1.0, 10.0} and {c.dt for c in pid} == {10.0}
    for runs in (retry, pid):
        assert {c.acceptance for c in runs} == {"strict"}
    assert {c.solver_key() for c in retry}.isdisjoint(
        {c.solver_key() for c in cases if c.controller == "constant"})
    assert {c.solver_key() for c in pid}.isdisjoint({c.solver_key() for c in retry})
    assert pid[0].build().error_estimate is True and retry[0].build().error_estimate is None
    damped = quick_grid(["pendulum"])
    assert len(damped) == 72 + 24 + 12  # the reference's accounting is not rerun
    assert quick_grid(["pendulum"], retry_dts=(), pid_dts=()) == [
        c for c in damped if c.controller == "constant"]
    with pytest.raises(ValueError, match="controller"):
        StabilityCase("pendulum", 1.0, "float64", 8, 8, "tanh", "projection",
                      controller="adaptive")


@pytest.mark.slow
def test_a_retry_case_runs_to_t1_and_reports_its_error():
    """Two steps of the oscillator under `RetryFailedSteps` (nothing to retry): the row says
    it reached t1, and its error there (one compilation, about 30 s)."""
    case = StabilityCase("harmonic_oscillator", 0.5, "float64", 8, 10, "tanh", "projection",
                         steps=2, controller="retry")
    row = run_case(case)
    assert row["result"] == "successful" and row["status"] == "ok", row
    assert row["reached"] is True and row["t_end"] == 1.0
    assert (row["steps_done"], row["rejected"]) == (2, 0)
    assert row["err_t1"] < 1e-12 and row["ham_drift"] < 1e-12
