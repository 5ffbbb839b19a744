"""The long-run study (`diffrax_vi.bench.long_run`): a tiny configuration end to end, the
reference and growth-exponent helpers, and the command line's wiring (without running the
quick study, which takes minutes)."""

import csv
import dataclasses
import math
import os

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

from diffrax_vi.bench import Adaptive, Fixed
from diffrax_vi.bench import long_run as lr
from diffrax_vi.bench.__main__ import main as cli_main
from diffrax_vi.problems import harmonic_oscillator, kepler


def test_tiny_study_writes_csv_report_and_figures(tmp_path):
    out = str(tmp_path)
    problems = {"harmonic_oscillator": dataclasses.replace(
        lr.PROBLEMS["harmonic_oscillator"], quick_spans=(3,), steps=(2, 4), sie_steps=(50,))}
    peers = [Adaptive("Dopri8", diffrax.Dopri8(), atol_ratio=1.0),
             Fixed("SemiImplicitEuler", diffrax.SemiImplicitEuler(), separable=True)]
    rows = lr.run_study(out, problems=problems,
                        solvers={"CGVI(7) round-off": lr.VARIATIONAL["CGVI(7) round-off"]},
                        peers=peers, rtols=(1e-10,), saves=40, repeats=1)
    assert len(rows) == 2 + 1 + 1 == lr.plan_size(
        problems, {"harmonic_oscillator": (3,)}, {"CGVI(7) round-off": None}, peers, (1e-10,))

    with open(os.path.join(out, lr.CSV_NAME), newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == lr.COLUMNS
        written = list(reader)
    assert len(written) == len(rows)
    for r in written:
        assert r["status"], r
        if r["status"] == "ok":
            for key in ("error", "energy_error", "wall_s"):
                assert math.isfinite(float(r[key])), (key, r)
    assert {r["status"] for r in written} == {"ok"}
    ours = [r for r in rows if r["family"] == "ours"]
    assert [r["value"] for r in ours] == [6, 12] and all(r["it_mean"] > 0 for r in ours)
    assert all(r["steps_per_period"] in (2, 4) for r in ours)
    # The peer's energy is read at its step ends, its dense-output value kept apart.
    dopri = next(r for r in rows if r["solver"] == "Dopri8")
    assert dopri["energy_error_dense"] is not None

    for name in ("report.md", "harmonic_oscillator_error.png", "harmonic_oscillator_energy.png",
                 lr.SERIES_NAME, lr.REFERENCE_NAME, "energy_growth.png"):
        assert os.path.getsize(os.path.join(out, name)) > 0, name
    report = open(os.path.join(out, "report.md")).read()
    assert "## Cheapest run per final error" in report
    assert "CGVI(7) round-off" in report and "Dopri8" in report


def test_failed_and_skipped_runs_are_recorded_but_never_count():
    rows = [
        dict(solver="a", status="ok", error=1e-9, wall_s=2.0, family="ours"),
        dict(solver="a", status="maxiter", error=1e-12, wall_s=0.1, family="ours"),
        dict(solver="a", status="skipped", error=None, wall_s=None, family="ours"),
    ]
    assert lr.cheapest(rows, 1e-8)["wall_s"] == 2.0
    assert lr.cheapest(rows, 1e-10) is None


def test_growth_exponent_recovers_a_power_law():
    t = np.linspace(0.0, 1e4, 2001)[1:]
    assert lr.growth_exponent(t, 1e-16 * t**0.5) == pytest.approx(0.5, abs=1e-6)
    assert lr.growth_exponent(t, np.full_like(t, 1e-12)) == pytest.approx(0.0, abs=1e-9)
    assert lr.growth_exponent(t[:4], t[:4]) is None  # too few points


def test_extended_precision_closed_forms_match_the_problems():
    ho = harmonic_oscillator(dtype=jnp.float64)
    for problem, t1 in ((ho, 7.3), (kepler(0.9, dtype=jnp.float64), 11.0)):
        ref = lr.reference_end(problem, t1)
        assert "closed form" in ref.method
        np.testing.assert_allclose(ref.q, problem.reference(np.array([t1]))[0][0], atol=1e-13)


def test_cli_parses_long_run(monkeypatch, tmp_path):
    seen = {}

    def fake_run_study(out, **kwargs):
        seen.update(out=out, **kwargs)
        return []

    monkeypatch.setattr(lr, "run_study", fake_run_study)
    out = str(tmp_path / "lr")
    cli_main(["long-run", "--quick", "--solvers", "CGVI", "--problems", "harmonic_oscillator",
              "--out", out, "--no-progress"])
    assert seen["out"] == out
    assert list(seen["problems"]) == ["harmonic_oscillator"]
    assert list(seen["solvers"]) == [
        "CGVI(7) round-off", "CGVI(7)", "CGVI(7) chord", "CGVI(7) chord round-off",
        "CGVI(7) kinetic round-off", "CGVI(7) reference form"
    ]
    assert seen["full"] is False and seen["spans"] is None
    assert seen["command"].startswith("python -m diffrax_vi.bench long-run --quick")
    cli_main(["long-run", "--full", "--spans", "1000", "--problems", "harmonic_oscillator",
              "kepler_e0.5", "--out", out, "--no-progress"])
    assert seen["full"] is True
    assert seen["spans"] == {"harmonic_oscillator": (1000,), "kepler_e0.5": (1000,)}
    with pytest.raises(SystemExit, match="--spans"):
        cli_main(["long-run", "--spans", "0", "--out", out, "--no-progress"])
    with pytest.raises(SystemExit):
        cli_main(["long-run", "--problems", "nope", "--out", out, "--no-progress"])
    with pytest.raises(SystemExit):
        cli_main(["long-run", "--solvers", "nope", "--out", out, "--no-progress"])


def test_long_runs_are_predicted_from_shorter_spans_and_fewer_steps():
    fixed = Fixed("CGVI", diffrax.SemiImplicitEuler())
    adaptive = Adaptive("Dopri8", diffrax.Dopri8())
    walls = {("CGVI", 4): (100, 2.0), ("Dopri8", 1e-12): (100, 1.0)}
    assert lr._predicted_wall(walls, fixed, 4, 1000) == pytest.approx(20.0)  # 10x the span
    assert lr._predicted_wall(walls, fixed, 8, 100) == pytest.approx(4.0)  # 2x the steps
    assert lr._predicted_wall(walls, adaptive, 1e-12, 10_000) == pytest.approx(100.0)
    assert lr._predicted_wall(walls, adaptive, 1e-13, 100) is None


def test_reference_of_a_time_dependent_problem_checks_against_scipy_at_the_absolute_time():
    """Without a GBS step the reference is the problem's own, checked by scipy's DOP853 on the
    field at the absolute time (the modulated oscillator's frequency depends on it)."""
    from diffrax_vi.problems import modulated_oscillator

    problem = modulated_oscillator(dtype=jnp.float64)
    ref = lr.reference_end(problem, 25.0)
    assert ref.error is not None and ref.error < 1e-11
