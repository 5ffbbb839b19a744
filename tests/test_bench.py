"""The benchmark harness (`diffrax_vi.bench`): status classification, cost at equal error, and
smoke runs of every study on tiny grids (CSV, markdown and PNG written to `tmp_path`)."""

from __future__ import annotations

import dataclasses
import os
import re

import diffrax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._root_finder.damped_newton import LevenbergMarquardt
from diffrax_vi.bench import (
    Adaptive,
    Fixed,
    SciPy,
    StabilityCase,
    classify,
    convergence_rates,
    long_time_energy,
    quick_grid,
    read_rows,
    report,
    stability_sweep,
    work_precision,
)
from diffrax_vi.bench.__main__ import main as cli_main
from diffrax_vi.bench.stability import full_grid


@dataclasses.dataclass
class _FakeSolution:
    result: object
    ys: tuple = (np.zeros((2, 1)), np.zeros((2, 1)))
    ts: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 1.0]))
    solver_state: object = None


@dataclasses.dataclass
class _State:
    max_iterations: int


@pytest.mark.parametrize(
    "member, expected",
    [
        (diffrax.RESULTS.successful, "ok"),
        (diffrax.RESULTS.promote(optx.RESULTS.nonlinear_max_steps_reached), "maxiter"),
        (diffrax.RESULTS.promote(optx.RESULTS.nonlinear_divergence), "diverged"),
        (diffrax.RESULTS.promote(optx.RESULTS.nonfinite), "nonfinite"),
        (diffrax.RESULTS.promote(optx.RESULTS.singular), "singular"),
        (diffrax.RESULTS.max_steps_reached, "error:max_steps_reached"),
        (diffrax.RESULTS.dt_min_reached, "diverged"),
        (optx.RESULTS.nonlinear_divergence, "diverged"),
    ],
)
def test_classify_result_members(member, expected):
    assert classify(_FakeSolution(member)) == expected


def test_classify_nonfinite_success_cap_and_exceptions():
    nan = (np.array([[0.0], [np.nan]]), np.zeros((2, 1)))
    assert classify(_FakeSolution(diffrax.RESULTS.successful, ys=nan)) == "nonfinite"
    # padding past the last saved step (SaveAt(steps=True)) is not the final state
    padded = (np.array([[0.0], [1.0], [np.inf]]), np.zeros((3, 1)))
    ts = np.array([0.0, 1.0, np.inf])
    assert classify(_FakeSolution(diffrax.RESULTS.successful, ys=padded, ts=ts)) == "ok"
    # a failed solve whose solver state hit the iteration cap is `maxiter`
    diverged = diffrax.RESULTS.promote(optx.RESULTS.nonlinear_divergence)
    sol = _FakeSolution(diverged, solver_state=_State(max_iterations=50))
    assert classify(sol, iteration_cap=50) == "maxiter"
    assert classify(sol, iteration_cap=100) == "diverged"
    assert classify(ZeroDivisionError("x")) == "error:ZeroDivisionError"
    with pytest.raises(TypeError, match="classify takes"):
        classify(object())


def test_classify_scipy():
    from scipy.integrate import solve_ivp

    good = solve_ivp(lambda t, y: -y, (0, 1), [1.0], method="DOP853")
    assert classify(good) == "ok"
    failed = dataclasses.replace(_FakeSolution(None), ys=None)  # shape of an OdeResult:
    failed.status, failed.y, failed.message = -1, np.ones((1, 3)), "step size too small"
    assert classify(failed) == "diverged"
    failed.status, failed.y = 0, np.array([[1.0, np.nan]])
    assert classify(failed) == "nonfinite"


def test_time_at_error_and_ratios():
    def rows(solver, family, pts):
        return [dict(problem="p", solver=solver, family=family, status="ok", error=e, wall_s=w)
                for w, e in pts]

    ours = rows("nvi", "ours", [(1.0, 1e-6), (2.0, 1e-10), (4.0, 1e-14)])
    peer = rows("rk", "peer", [(0.1, 1e-4), (1.0, 1e-8), (3.0, 1e-9)])
    peer.append(dict(problem="p", solver="rk", family="peer", status="maxiter", error=1e-20,
                     wall_s=0.01))  # not converged: ignored
    t, how = report.time_at_error(ours, 1e-8)
    assert how == "interpolated" and t == pytest.approx(2**0.5)
    assert report.time_at_error(peer, 1e-12) == (None, "unreachable")
    assert report.time_at_error(peer, 1e-3) == (0.1, "at most")
    table = {r["target"]: r for r in report.ratio_table(ours + peer, (1e-8, 1e-12))}
    assert table[1e-8]["ratio"] == pytest.approx(2**0.5 / 1.0)
    assert table[1e-12]["peer"] is None and table[1e-12]["ratio"] is None
    assert "unreachable" in report.ratio_markdown(list(table.values()))


def test_the_plotted_front_is_ordered_by_error_and_never_turns_back():
    """The figure's curve of a solver: its points that no other beats in both error and
    time, most accurate first; a slower, less accurate point and a failed one are left off."""
    pts = [(1e-6, 1.0), (1e-14, 4.0), (1e-10, 2.0), (1e-9, 3.0), (1e-12, 1.5)]
    rows = [dict(problem="p", solver="s", family="peer", status="ok", error=e, wall_s=w)
            for e, w in pts]
    rows.append(dict(problem="p", solver="s", family="peer", status="diverged", error=1e-16,
                     wall_s=0.1))
    front = report.work_precision_front(rows)
    assert front == [(1e-14, 4.0), (1e-12, 1.5), (1e-6, 1.0)]
    errors, times = zip(*front, strict=True)
    assert list(errors) == sorted(errors) and list(times) == sorted(times, reverse=True)


def test_quick_grid_is_the_reference_grid():
    every = quick_grid(retry_dts=(), pid_dts=())  # retry and PID runs: test_stability_target
    assert len(every) == 216  # once with our convergence test, once with the reference's
    assert {c.acceptance for c in every} == {"strict", "reference"}
    cases = [c for c in every if c.acceptance == "strict"]
    assert len(cases) == 108 and all(c.max_iterations == 1000 for c in cases)
    for problem, (s, r) in {"harmonic_oscillator": (10, 8), "pendulum": (8, 8),
                            "double_pendulum": (10, 16)}.items():
        mine = [c for c in cases if c.problem == problem]
        assert len(mine) == 36 and {(c.width, c.nodes) for c in mine} == {(s, r)}
    assert {c.dt for c in cases} == {0.1, 1.0, 10.0}
    assert {c.activation for c in cases} == {"gelu", "tanh"}
    # λ is the reference's shift of J + λI for RegularisedNewton; LevenbergMarquardt keeps
    # its own damping scale.
    newton = next(c for c in cases if c.dtype == "float64" and c.solver == "RegularisedNewton")
    assert newton.lam_value == pytest.approx(16 * np.sqrt(np.finfo(np.float64).eps))
    assert newton.build().root_finder.lam == pytest.approx(newton.lam_value)
    lm = next(c for c in cases if c.solver == "LevenbergMarquardt")
    assert lm.build().root_finder.lam == LevenbergMarquardt.lam
    reference = next(c for c in every if c.acceptance == "reference")
    assert reference.build().root_finder.convergence == "reference"
    strict = dataclasses.replace(reference, acceptance="strict")
    assert reference.solver_key() == strict.solver_key()  # one compilation serves both
    # λ is traced too: the full grid's five RegularisedNewton shifts share one compilation
    full = full_grid(problems=("harmonic_oscillator",))
    assert len(full) == 11_664 and len({c.solver_key() for c in full}) == 972
    with pytest.raises(ValueError, match="unknown activation"):
        StabilityCase("pendulum", 0.1, "float64", 8, 8, "swish", "LevenbergMarquardt")
    with pytest.raises(ValueError, match="acceptance"):
        StabilityCase("pendulum", 0.1, "float64", 8, 8, "tanh", "LevenbergMarquardt",
                      acceptance="loose")


@pytest.mark.slow
def test_work_precision_and_energy_smoke(tmp_path):
    ho = problems.harmonic_oscillator(dtype=jnp.float64, t1=1.0)
    # the polynomial member of the NetworkVI family: the same solver path, a lighter compile
    nvi = Fixed("NetworkVI", dvi.CGVI(3), family="ours")
    sie = Fixed("SemiImplicitEuler", diffrax.SemiImplicitEuler(), separable=True)
    entries = [nvi, sie, Adaptive("Tsit5", diffrax.Tsit5()), SciPy()]
    path = str(tmp_path / "wp.csv")
    rows = work_precision(ho, entries, steps={"NetworkVI": [5, 10], "SemiImplicitEuler": [10, 100]},
                          rtols=[1e-5, 1e-9], repeats=1, csv_path=path)
    statuses = [(r["solver"], r["value"], r["status"], r.get("message")) for r in rows]
    assert len(rows) == 8 and all(r["status"] == "ok" for r in rows), statuses
    by = {(r["solver"], r["value"]): r for r in rows}
    assert by[("NetworkVI", 10)]["error"] < 1e-6
    assert by[("NetworkVI", 10)]["iterations"] > 0 and by[("NetworkVI", 10)]["steps"] == 10
    assert by[("SemiImplicitEuler", 100)]["error"] < by[("SemiImplicitEuler", 10)]["error"]
    assert by[("Tsit5", 1e-9)]["error"] < by[("Tsit5", 1e-5)]["error"]
    assert by[("scipy DOP853", 1e-9)]["error"] < 1e-7
    assert all(r["energy_error"] is not None and r["wall_s"] > 0 for r in rows)
    assert len(read_rows(path)) == 8

    # a problem that is not separable gets one isolated error row for SemiImplicitEuler
    pend = problems.pendulum(dtype=jnp.float64)
    (row,) = work_precision(pend, [sie], steps=[10, 20], repeats=1)
    assert row["status"] == "error:NotSeparable"

    long = long_time_energy(ho.with_span(20.0), [(sie, 200), (SciPy(), 1e-6)], samples=5,
                            csv_path=str(tmp_path / "energy.csv"))
    assert len(long) == 10 and all(r["status"] == "ok" for r in long)
    sie_err = [r["energy_error"] for r in long if r["solver"] == "SemiImplicitEuler"]
    assert sie_err == sorted(sie_err)  # a running maximum

    report.plot_work_precision(rows, tmp_path / "wp.png")
    report.plot_energy(long, tmp_path / "energy.png")
    assert "NetworkVI" in report.work_precision_table(rows)
    assert os.path.getsize(tmp_path / "wp.png") > 1000
    assert os.path.getsize(tmp_path / "energy.png") > 1000


def test_fixed_entries_may_retry_failed_steps():
    """`Fixed(..., retry=True)` steps with RetryFailedSteps: the run that fails at h = 3 with
    constant steps goes to the end, and the row counts the failed trials."""
    ho = problems.harmonic_oscillator(dtype=jnp.float64, t1=24.0)
    # the all-parameter step, which fails at h = 3 (the projected one solves any oscillator step)
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8), formulation=dvi.FreeEndpoints()
    )
    plain = Fixed("NetworkVI", solver, family="ours")
    retry = Fixed("NetworkVI retry", solver, family="ours", retry=True)
    assert retry.step_budget(8) > plain.step_budget(8) == 8
    rows = work_precision(ho, [plain, retry], steps=[8], repeats=1)
    by = {r["solver"]: r for r in rows}
    assert by["NetworkVI"]["status"] == "diverged"
    assert by["NetworkVI retry"]["status"] == "ok", by["NetworkVI retry"]
    assert by["NetworkVI retry"]["rejected"] > 0
    assert by["NetworkVI retry"]["steps"] == 8 + by["NetworkVI retry"]["rejected"]
    assert by["NetworkVI retry"]["error"] < 1e-6


@pytest.mark.slow
def test_stability_sweep_smoke(tmp_path):
    # the reference's harmonic-oscillator setting; dt = 10 does not converge (one compilation)
    base = StabilityCase("harmonic_oscillator", 0.1, "float64", 8, 10, "tanh",
                         "LevenbergMarquardt")
    path = str(tmp_path / "stability.csv")
    lax = dataclasses.replace(base, dt=10.0, acceptance="reference")
    # λ is a traced input of the same compilation: an overdamped LM (μ = 1e6‖F‖) crawls
    crawl = dataclasses.replace(base, lam=1e6)
    rows = stability_sweep([dataclasses.replace(base, dt=10.0), base, lax, crawl],
                           csv_path=path)
    (crawl_row,) = [r for r in rows if r["lam"] == 1e6]
    rows = [r for r in rows if r["lam"] != 1e6]
    (base_row,) = [r for r in rows if r["dt"] == 0.1]
    assert crawl_row["iterations"] > 2 * base_row["iterations"]  # measured 23 against 10
    # the reference's accounting never fails a stalled solve (same compilation, the test is
    # a traced flag): its dt = 10 steps either stall and pass as converged, or crawl on to
    # the iteration cap; which of the two happens moves with rounding (both were measured)
    (lax_row,) = [r for r in rows if r["acceptance"] == "reference"]
    assert lax_row["status"] in ("ok", "maxiter")
    assert lax_row["status"] == "maxiter" or lax_row["steps_done"] == 10
    rows = [r for r in rows if r["acceptance"] == "strict"]
    by = {r["dt"]: r for r in rows}
    ok = by[0.1]
    assert ok["status"] == "ok", ok
    assert ok["ref_err"] < 1e-10 and ok["ham_drift"] < 1e-10 and ok["steps_done"] == 10
    assert ok["result"] == "successful" and ok["err_t1"] < 1e-10
    assert by[10.0]["status"] == "diverged"  # the same stall fails our test
    assert by[10.0]["steps_done"] < 10 and by[10.0].get("ref_err") is None
    assert by[10.0]["result"] not in (None, "successful")  # a loud failure, not a wrong one
    assert [r["status"] for r in read_rows(path)
            if r["acceptance"] == "strict" and float(r["lam"]) != 1e6] == [
        r["status"] for r in rows]
    rates = convergence_rates(rows)["float64"]
    assert (rates["cases"], rates["converged"], rates["rate"]) == (2, 1, 0.5)
    report.plot_convergence_heatmap(rows, tmp_path / "heat.png")
    assert os.path.getsize(tmp_path / "heat.png") > 1000
    assert "reference rate" in report.stability_table(rows)


def test_cli_report(tmp_path):
    # scipy only: no compilation, so the command line and the report run end to end quickly
    out = str(tmp_path / "out")
    cli_main(["work-precision", "--problems", "harmonic_oscillator", "--solvers", "scipy",
              "--repeats", "1", "--no-progress", "--out", out])
    text = open(os.path.join(out, "report.md")).read()
    assert "scipy DOP853" in text and "Work-precision" in text
    assert os.path.exists(os.path.join(out, "work_precision.png"))
    with pytest.raises(SystemExit):
        cli_main(["work-precision", "--problems", "nope", "--out", out])


def test_cli_parallel_parts_are_merged(tmp_path):
    # two problems as two worker processes; their CSVs are concatenated in problem order
    out = str(tmp_path / "out")
    cli_main(["work-precision", "--problems", "harmonic_oscillator", "pendulum", "--solvers",
              "scipy", "--repeats", "1", "--jobs", "2", "--no-progress", "--out", out])
    rows = read_rows(os.path.join(out, "work_precision.csv"))
    assert [r["problem"] for r in rows] == ["harmonic_oscillator"] * 5 + ["pendulum"] * 5
    assert all(r["status"] == "ok" for r in rows)
    text = open(os.path.join(out, "report.md")).read()
    assert "Wall time of the run" in text and "pendulum" in text
    with pytest.raises(SystemExit):
        cli_main(["stability", "--jobs", "0", "--out", out])


def test_parallel_workers_get_their_own_cpus():
    """Each worker of the embedded cluster gets a disjoint share of the CPUs
    (`executor.cpu_slots`); with more workers than CPUs none is pinned."""
    from diffrax_vi.bench.executor import cpu_slots

    if not hasattr(os, "sched_getaffinity"):
        assert cpu_slots(2) == [None, None]
        return
    own = os.sched_getaffinity(0)
    slots = cpu_slots(2)
    if len(own) >= 2:
        assert all(slots) and not slots[0] & slots[1] and slots[0] | slots[1] == own
    else:
        assert slots == [None, None]
    assert cpu_slots(len(own) + 1) == [None] * (len(own) + 1)


def test_harness_refuses_bad_input():
    problem = problems.harmonic_oscillator()
    tsit5 = Adaptive("Tsit5", diffrax.Tsit5())
    cgvi = Fixed("CGVI", dvi.CGVI(3))
    with pytest.raises(TypeError, match="Fixed, Adaptive or SciPy"):
        work_precision(problem, [diffrax.Tsit5()], rtols=[1e-6])
    with pytest.raises(ValueError, match="CGVI: the step count must be a positive number"):
        work_precision(problem, [cgvi], steps=[0])
    with pytest.raises(ValueError, match="CGVI: the step count must be an integer"):
        work_precision(problem, [cgvi], steps=[2.5])
    with pytest.raises(ValueError, match="Tsit5: the rtol must be a positive number"):
        work_precision(problem, [tsit5], rtols=[float("nan")])
    with pytest.raises(ValueError, match="repeats"):
        work_precision(problem, [tsit5], rtols=[1e-6], repeats=0)
    with pytest.raises(ValueError, match="Tsit5: the rtol must be a positive number"):
        long_time_energy(problem, [(tsit5, -1e-6)])
    with pytest.raises(ValueError, match="samples"):
        long_time_energy(problem, [(tsit5, 1e-6)], samples=1)


def test_energy_retry_flag_reaches_the_networkvi_entries_and_the_workers():
    from diffrax_vi.bench.__main__ import _our_energy_entries
    from diffrax_vi.bench.suites import SETTINGS

    setting = SETTINGS["double_pendulum"]
    plain = _our_energy_entries(setting, False)
    retry = _our_energy_entries(setting, True)
    assert not any(e.retry for e in plain)
    assert all(e.retry and e.name == f"{p.name} retry" for e, p in zip(retry, plain, strict=True))


def test_energy_problem_selection():
    """Quick energy runs skip problems whose setting says so (the Toda lattice); --full and
    an explicit --problems list run them."""
    from diffrax_vi.bench.__main__ import _energy_problems
    from diffrax_vi.bench.suites import SETTINGS

    quick = _energy_problems(None, False, SETTINGS)
    assert "toda_lattice" not in quick and "harmonic_oscillator" in quick
    assert _energy_problems(None, True, SETTINGS) == list(SETTINGS)
    assert _energy_problems(["toda_lattice"], False, SETTINGS) == ["toda_lattice"]


def test_published_suites_hold_the_documented_networkvi_settings():
    """The quick work-precision study compares the warm start and the fast settings, the
    energy study the warm start and the long-run settings (docs/how-to/choosing.md)."""
    from diffrax_vi.bench.suites import SETTINGS, energy_entries, networkvi_entries

    setting = SETTINGS["harmonic_oscillator"]
    warm, fast, projected = networkvi_entries(setting, False)
    assert warm.name.endswith("warm") and isinstance(
        warm.solver.seed.initial_trajectory, dvi.PreviousStep)
    assert fast.name.endswith("fast") and fast.solver.seed.reuse_neurons
    assert fast.solver.root_finder.settle == 0 and fast.solver.root_finder.jacobian == "auto"
    assert projected.name == "NetworkVI tanh10 R8 projection" and projected.family == "ours"
    assert isinstance(projected.solver.formulation, dvi.VariableProjection)
    assert isinstance(projected.solver.formulation.hidden, dvi.UniformLayer)
    assert isinstance(projected.solver.root_finder, dvi.RoundoffNewton)
    assert len(networkvi_entries(setting, True)) == 5
    first, long_run = energy_entries(setting)
    assert first.name == warm.name and long_run.name.endswith("long-run")
    policy = long_run.solver.seed
    assert policy.reuse_neurons and policy.refit_residual == pytest.approx(
        2048 * np.finfo(np.float64).eps)
    assert {e.family for e in (warm, fast, first, long_run)} == {"ours"}


def test_stability_sweep_runs_the_projected_step_on_request(tmp_path):
    """`--solvers projection` adds the projected step (`VariableProjection()` with its
    `RoundoffNewton`) to the sweep: our convergence test only, λ = 0, not in the default
    grids (which stay the reference's)."""
    from diffrax_vi.bench.stability import run_case, select_solvers

    assert select_solvers(None) == ("LevenbergMarquardt", "RegularisedNewton")
    assert select_solvers(["projection"]) == ("projection",)
    assert select_solvers(["Newton", "proj"]) == ("RegularisedNewton", "projection")
    with pytest.raises(ValueError, match="match"):
        select_solvers(["DogLeg"])
    with pytest.raises(SystemExit):
        cli_main(["stability", "--solvers", "DogLeg", "--out", str(tmp_path)])
    cases = quick_grid(solvers=("projection",), retry_dts=(), pid_dts=())
    assert len(cases) == 54 and {c.acceptance for c in cases} == {"strict"}
    assert {c.solver for c in quick_grid()} == {"LevenbergMarquardt", "RegularisedNewton"}
    case = next(c for c in cases if c.problem == "harmonic_oscillator")
    assert case.lam_value == 0.0
    solver = case.build(reference=jnp.asarray(True), lam=jnp.asarray(1.0))
    assert isinstance(solver.formulation, dvi.VariableProjection)
    assert isinstance(solver.root_finder, dvi.RoundoffNewton)
    assert solver.root_find_max_steps == case.max_iterations == 1000
    with pytest.raises(ValueError, match="only our convergence test"):
        dataclasses.replace(case, acceptance="reference")
    with pytest.raises(ValueError, match="undamped"):
        dataclasses.replace(case, lam=1e-3)
    full = full_grid(problems=("harmonic_oscillator",), solvers=("projection",))
    assert len(full) == 648 and len({c.solver_key() for c in full}) == 162
    with pytest.raises(ValueError, match="unknown solver"):
        full_grid(solvers=("DogLeg",))
    # two steps through the sweep's compiled solve (the traced λ and flag go unused)
    row = run_case(dataclasses.replace(case, dt=0.1, dtype="float64", activation="tanh",
                                       steps=2))
    assert row["status"] == "ok" and row["steps_done"] == 2 and row["ref_err"] < 1e-12


def benchmark_script(name: str):
    """The benchmark script `benchmarks.<name>` (run as `python -m benchmarks.<name>`)."""
    import importlib

    return importlib.import_module(f"benchmarks.{name}")


BENCHMARKS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks")
QUOTED_MODULE = re.compile(r"-m\s+benchmarks\.(\w+)")
QUOTED_PATH = re.compile(r"(?<![:\w])benchmarks/(\w+)\.py\b")  # not `git show REV:benchmarks/...`


# Records, left out of the scan: the changelog, and the studies page, whose commands run at the
# git tag it names (the settled studies left main).
RECORDS = ("changelog.md", "studies.md")


def quoting_files() -> list[str]:
    """The pages, the Makefile, the tests and the scripts themselves: every place that quotes
    a benchmark command (the records and the result files are left out)."""
    root = os.path.dirname(BENCHMARKS)
    docs = [os.path.join(d, f) for d, _, fs in os.walk(os.path.join(root, "docs"))
            for f in fs if f.endswith(".md") and f not in RECORDS]
    scripts = [os.path.join(BENCHMARKS, f) for f in os.listdir(BENCHMARKS) if f.endswith(".py")]
    tests = [os.path.join(root, "tests", f) for f in os.listdir(os.path.join(root, "tests"))
             if f.endswith(".py")]
    return sorted(docs + scripts + tests + [os.path.join(root, name) for name in
                                            ("README.md", "Makefile", "benchmarks/README.md")])


def test_quoted_benchmark_commands_name_existing_scripts():
    """Every `python -m benchmarks.<name>` and every `benchmarks/<name>.py` quoted in the
    docs, the README files, the Makefile, the tests and the scripts names a script that is
    there, no command still runs a script by its path, and the index
    (`benchmarks/README.md`) lists every script."""
    scripts = {f[:-3] for f in os.listdir(BENCHMARKS) if f.endswith(".py")} - {"__init__"}
    missing, by_path = [], []
    for path in quoting_files():
        with open(path, encoding="utf-8") as file:
            text = file.read()
        for name in QUOTED_MODULE.findall(text) + QUOTED_PATH.findall(text):
            if name not in scripts:
                missing.append(f"{os.path.relpath(path, BENCHMARKS)}: {name}")
        by_path += [f"{os.path.relpath(path, BENCHMARKS)}: {m.group(0)}" for m in
                    re.finditer(r"python\S*\s+(?:-u\s+)?benchmarks/\w+\.py", text)]
    assert not missing, f"quoted benchmark scripts that do not exist: {missing}"
    assert not by_path, f"commands that run a benchmark by its path: {by_path}"
    with open(os.path.join(BENCHMARKS, "README.md"), encoding="utf-8") as file:
        index = file.read()
    unlisted = [n for n in sorted(scripts - {"common"}) if f"benchmarks.{n} " not in index
                and f"benchmarks.{n}`" not in index]
    assert not unlisted, f"scripts missing from benchmarks/README.md: {unlisted}"


def test_benchmark_scripts_use_no_private_names_of_the_package_or_each_other():
    """No script imports a private (underscore) name of `diffrax_vi` or of another script,
    or reads one as an attribute of such a module (`quadrature._split`); no script edits
    `sys.path`."""
    import ast

    ours = ("diffrax_vi", "benchmarks")
    found = []
    for file in sorted(f for f in os.listdir(BENCHMARKS) if f.endswith(".py")):
        with open(os.path.join(BENCHMARKS, file), encoding="utf-8") as handle:
            source = handle.read()
        if "sys.path" in source:
            found.append(f"{file}: edits sys.path")
        tree = ast.parse(source)
        modules = set()  # local names bound to modules of ours
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] in ours:
                        modules.add(alias.asname or alias.name.split(".")[0])
                        if any(part.startswith("_") for part in alias.name.split(".")):
                            found.append(f"{file}: import {alias.name}")
            elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in ours:
                for alias in node.names:
                    modules.add(alias.asname or alias.name)  # a submodule or a public name
                    if alias.name.startswith("_") or any(
                            part.startswith("_") and part != "__main__"
                            for part in node.module.split(".")):
                        found.append(f"{file}: from {node.module} import {alias.name}")
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                    and not node.attr.startswith("__") and isinstance(node.value, ast.Name)
                    and node.value.id in modules):
                found.append(f"{file}: {node.value.id}.{node.attr}")
    assert not found, f"private names used by benchmark scripts: {found}"


@pytest.mark.slow  # a study script's report (benchmarks/), not the package
def test_root_existence_script_reports_each_seed(capsys):
    """benchmarks.root_existence: one row per seed and step length; a short oscillator
    step converges and is accurate, a failed one reports the stalled iterate's error."""
    module = benchmark_script("root_existence")
    module.main(["harmonic_oscillator", "tanh", "10", "8", "--dts", "0.1", "10",
                 "--seeds", "OGA1d (10 sub-steps)"])
    out = capsys.readouterr().out
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in out.splitlines()
            if line.startswith("| 0.1 |") or line.startswith("| 10 |")]
    (short, long) = rows
    assert short[2] == "True" and float(short[4]) < 1e-12 and float(short[5]) < 1e-12
    # dt = 10 stalls far from a root (measured residual 0.31), yet ends near the motion
    assert long[2] == "False" and float(long[4]) > 1e-3 and np.isfinite(float(long[5]))
    with pytest.raises(SystemExit):
        module.main(["harmonic_oscillator", "tanh", "10", "8", "--dts", "0"])


def test_iteration_summary_reads_the_solver_counters():
    from types import SimpleNamespace

    from diffrax_vi.bench import iteration_summary, timed

    # 5 steps: iterations 2, 2, 3, 3, 7 (histogram index = iterations)
    hist = np.zeros(9, int)
    hist[[2, 3, 7]] = [2, 2, 1]
    state = SimpleNamespace(steps=5, histogram=hist, iterations=17, max_iterations=7)
    assert iteration_summary(state) == dict(steps=5, it_median=3, it_mean=3.4, it_max=7)
    empty = SimpleNamespace(steps=0, histogram=np.zeros(9, int), iterations=0, max_iterations=0)
    assert iteration_summary(empty)["it_median"] is None
    out, seconds = timed(lambda x: x + 1, np.float64(1.0))
    assert out == 2.0 and seconds >= 0
