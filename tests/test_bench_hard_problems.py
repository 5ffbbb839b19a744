"""The hard-problem study (`benchmarks/hard_problems.py`, issue 31): the verdict on constructed
fronts, and a tiny run that records a failed solve as failed."""

from __future__ import annotations

import math
import os

import pytest

import diffrax_vi as dvi
from benchmarks import hard_problems as hp
from diffrax_vi.bench import read_rows


def _row(solver, wall, error, status="ok", problem="p"):
    return dict(problem=problem, solver=solver, wall_s=wall, error=error, status=status,
                energy_error=error, steps_per_period=None, value=1.0)


def test_front_keeps_pareto_points_and_clips_at_the_floor():
    rows = [_row("a", 1.0, 1e-3), _row("a", 2.0, 1e-2), _row("a", 3.0, 1e-6),
            _row("a", 0.5, 1.0, status="maxiter"), _row("a", 4.0, 1e-15),
            _row("a", 5.0, 1e-16)]
    assert hp.front(rows) == [(1.0, 1e-3), (3.0, 1e-6), (4.0, 1e-15), (5.0, 1e-16)]
    assert hp.front(rows, floor=1e-12) == [(1.0, 1e-3), (3.0, 1e-6), (4.0, 1e-12)]


def test_ratios_interpolate_on_the_overlap_only():
    baseline = [(1.0, 1e-2), (10.0, 1e-6)]
    config = [(1.0, 1e-3), (10.0, 1e-7)]  # ten times more accurate at every time
    ratio, at, exact = hp.error_ratio(config, baseline)
    assert ratio == pytest.approx(10.0) and at in (1.0, 10.0) and exact
    # at equal error: the config reaches 1e-6 at 10^0.75 s (log-log), the baseline at 10 s
    ratio, at, exact = hp.time_ratio(config, baseline)
    assert ratio == pytest.approx(10.0 ** 0.25) and at == pytest.approx(1e-6) and exact
    # slack: the baseline gets 10x the time, so it is as accurate as the config
    assert hp.error_ratio(config, [(10.0, 1e-2), (100.0, 1e-6)], slack=10.0)[0] == \
        pytest.approx(10.0)
    # cheaper than every baseline run, or more accurate than any: no ratio
    assert hp.error_ratio([(0.1, 1e-9)], baseline) is None
    assert hp.time_ratio([(100.0, 1e-9)], baseline) is None
    # slower than the baseline's slowest run: its error there bounds the baseline's
    assert hp.error_ratio([(100.0, 1e-7)], baseline) == (pytest.approx(10.0), 100.0, False)
    # less accurate than the baseline's cheapest run: its time bounds the baseline's
    assert hp.time_ratio([(0.5, 1e-1)], baseline) == (pytest.approx(2.0), 1e-1, False)


def test_verdict_on_constructed_fronts():
    configs = {c.name: c for c in (
        hp.cgvi(4),
        hp.network("tanh", 10, 8, "uniform"),
        hp.network("tanh", 10, 8, "first seed"),
        hp.network("tanh", 10, 8, "seed"),
        hp.network("tanh", 10, 8, "all-parameter"),
    )}
    twin = "tanh 10, GL8"
    rows = [
        _row("CGVI(4)", 1.0, 1e-2), _row("CGVI(4)", 10.0, 1e-6),
        # frozen twin: as good as the linear front
        _row(f"{twin}, uniform", 1.0, 1e-2), _row(f"{twin}, uniform", 10.0, 1e-6),
        _row(f"{twin}, first seed", 1.0, 2e-2), _row(f"{twin}, first seed", 10.0, 2e-6),
        # 100x more accurate at every wall time: wins against both
        _row(f"{twin}, seed", 1.0, 1e-4), _row(f"{twin}, seed", 10.0, 1e-8),
        # 2x only, and one failed run: no win
        _row(f"{twin}, all-parameter", 1.0, 5e-3), _row(f"{twin}, all-parameter", 10.0, 5e-7),
        _row(f"{twin}, all-parameter", 0.5, None, status="diverged"),
        _row("Dopri8", 0.1, 1e-10),
    ]
    vs = {v["solver"]: v for v in hp.verdicts(rows, configs, slack=1.0)}
    assert set(vs) == {f"{twin}, {h}" for h in hp.HIDDEN}
    assert all(v["wins"] is False for k, v in vs.items() if k != f"{twin}, seed")
    seed = vs[f"{twin}, seed"]
    assert seed["linear_error_ratio"] == pytest.approx(100.0)
    assert seed["twin_error_ratio"] == pytest.approx(100.0)  # against the better twin
    assert seed["linear_wins"] and seed["twin_wins"] and seed["wins"]
    # Dopri8's one run is cheaper and more accurate than all of them: a bound, far below 1
    assert seed["peers_error_ratio"] < 1 and seed["peers_error_ratio_exact"] is False
    allp = vs[f"{twin}, all-parameter"]
    assert allp["ok"] == 2 and allp["runs"] == 3
    assert allp["linear_best"] == pytest.approx(2.0, rel=0.3)
    assert not allp["linear_wins"] and not allp["wins"]
    uniform = vs[f"{twin}, uniform"]
    assert uniform["family"] == "frozen" and "twin_wins" not in uniform
    assert not uniform["wins"]  # only an adaptive configuration answers the question
    # the default slack gives the baseline more time: 1.25^4 less error where it is measured
    # (41x at 1 s), and at 10 s only a bound (the baseline's last run is at 10 s)
    config, baseline = [(1.0, 1e-4), (10.0, 1e-8)], [(1.0, 1e-2), (10.0, 1e-6)]
    assert hp.error_ratio(config[:1], baseline, hp.SLACK)[0] == pytest.approx(100 / 1.25**4)
    assert hp.error_ratio(config, baseline, hp.SLACK)[2] is False


def test_a_success_far_off_the_solution_is_recorded_as_escaped():
    configs = {"CGVI(8)": hp.cgvi(8)}
    rows = [_row("CGVI(8)", 1.0, 3e16, problem="henon_heiles"),
            _row("CGVI(8)", 2.0, 1e-9, problem="henon_heiles")]
    marked = hp.annotate(rows, configs, hp.PROBLEMS)
    assert [r["status"] for r in marked] == ["escaped", "ok"]
    assert marked[1]["dof"] == 9 and marked[1]["family"] == "linear"
    assert hp.front(marked) == [(2.0, 1e-9)]


@pytest.mark.long
def test_tiny_run_records_rows_and_failures(tmp_path):
    """Two steps per period of the oscillator: CGVI(2) runs, and a CGVI(2) allowed one Newton
    iteration a step fails; both are rows, the failure with its status and no error."""
    hard = hp.HardProblem("harmonic_oscillator", {}, 2 * math.pi * math.sqrt(2), "periods", 1,
                          math.sqrt(2), (4, 8), (4, 8))
    configs = [hp.cgvi(2),
               hp.Config("one iteration", "adaptive",
                         lambda: dvi.CGVI(2, max_iterations=1), 3, "x", "seed")]
    out = str(tmp_path)
    rows = hp.run_problem("oscillator", hard, configs, out, full=False, rtols=(1e-8,),
                          repeats=1, budget_s=0.1, peer_entries=hp.peers()[1:])
    # steps over the span of 1 + 1/8 periods: round(4.5) = 4, round(9) = 9
    assert [(r["solver"], r["value"]) for r in rows] == [
        ("CGVI(2)", 4), ("CGVI(2)", 9), ("one iteration", 4), ("one iteration", 9),
        ("Tsit5", 1e-8)]
    for r in rows:
        if r["solver"] == "one iteration":
            assert r["status"] != "ok" and r.get("error") is None
        else:
            assert r["status"] == "ok" and 0 < r["error"] < 1 and r["wall_s"] > 0
    text = hp.write_report(out, configs=configs, hards={"oscillator": hard})
    assert "no network configuration is 3x better" in text
    runs = read_rows(os.path.join(out, "runs.csv"))
    assert len(runs) == 5 and {r["dof"] for r in runs if r["solver"] == "CGVI(2)"} == {3}
    verdict = read_rows(os.path.join(out, "verdict.csv"))
    assert [v["solver"] for v in verdict] == ["one iteration"] and verdict[0]["ok"] == 0
    for name in ("report.md", "oscillator_fronts.png", "oscillator_dof.png"):
        assert os.path.getsize(os.path.join(out, name)) > 0
