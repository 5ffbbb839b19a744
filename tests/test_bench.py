"""The benchmark harness (`diffrax_vi.bench`): status classification, cost at equal error, and
smoke runs of every study on tiny grids (CSV, markdown and PNG written to `tmp_path`)."""

from __future__ import annotations

import dataclasses
import os
import re
import sys

import diffrax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
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
from diffrax_vi.nonlinear import LevenbergMarquardt


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


def test_quick_grid_is_the_reference_grid():
    every = quick_grid()
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
    assert by[10.0]["status"] == "diverged"  # the same stall fails our test
    assert by[10.0]["steps_done"] < 10 and by[10.0].get("ref_err") is None
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
    cases = quick_grid(solvers=("projection",))
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


def quoting_files() -> list[str]:
    """The pages, the Makefile, the tests and the scripts themselves: every place that quotes
    a benchmark command (the changelog and the result files are records, left out)."""
    root = os.path.dirname(BENCHMARKS)
    docs = [os.path.join(d, f) for d, _, fs in os.walk(os.path.join(root, "docs"))
            for f in fs if f.endswith(".md") and f != "changelog.md"]
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
    `sys.path`. Shared helpers are public names of `benchmarks.common`."""
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


def test_full_grid_sample_draws_whole_compilation_groups():
    """benchmarks.full_grid_sample: per solver, seeded random groups of cases that share a
    compilation (LevenbergMarquardt: 4 dt; RegularisedNewton: 4 dt x 5 λ)."""
    module = benchmark_script("full_grid_sample")
    strata = module.sample_groups("pendulum", 3, seed=1)
    assert sorted(strata) == ["LevenbergMarquardt", "RegularisedNewton"]
    for solver, (groups, total) in strata.items():
        assert total == 486 and len(groups) == 3
        for cases in groups:
            assert len({c.solver_key() for c in cases}) == 1
            assert len(cases) == (4 if solver == "LevenbergMarquardt" else 20)
    again = module.sample_groups("pendulum", 3, seed=1)
    assert [g[0][0] for g in again.values()] == [g[0][0] for g in strata.values()]


def test_speed_script_measures_the_ensemble_floor(monkeypatch):
    """benchmarks.speed's floor of an ensemble member: the vmapped LU solve of one Newton
    iteration of the projected step at the fixture's size (10 unknowns: 9 span coefficients
    and p_{n+1}), and the iterations of one member's solve; given the timer the ensembles
    used, it times that one instead of compiling another."""
    module = benchmark_script("speed")
    timer = module.floor_timer(4)
    monkeypatch.setattr(module, "floor_timer", lambda members: pytest.fail("compiled again"))
    per_member, iterations, n = module.linear_solve_floor(4, 1, timer)
    assert n == 10
    assert 0 < per_member < 0.1
    assert 10 <= iterations <= 10 * 100  # 10 steps, each 1 to root_find_max_steps


def test_speed_script_times_the_floor_in_the_rounds_of_each_ensemble(monkeypatch):
    """benchmarks.speed's fraction of the floor: each round times the floor after the
    ensemble, and a row reports the median over rounds of floor x members / ensemble time
    (a trivial member stands in for the solve, a constant for the floor's timing)."""
    module = benchmark_script("speed")

    def member(y0):
        return (2 * y0[0], y0[1]), jnp.array(True)

    monkeypatch.setattr(module, "solve_member", member)
    calls = []

    def floor():
        calls.append(1)
        return 1e-6

    _, rows = module.ensemble_figures(4, 2, 1, 3, floor=floor)
    assert len(calls) == 3 * len(rows) == 9  # once per round of each ensemble
    for row in rows:
        # the median of c·n/t over 3 rounds is c·n over the median time
        assert row["floor_fraction"] == pytest.approx(1e-6 * row["members"] / row["ens_s"])
    _, rows = module.ensemble_figures(4, 4, 1, 1)
    assert all(row["floor_fraction"] is None for row in rows)


@pytest.mark.parametrize(
    "only, expected", [(None, ["fixtures", "ensembles"]), ("fixtures", ["fixtures"]),
                       ("ensembles", ["ensembles"])],
)
def test_speed_script_runs_the_sections_asked_for(monkeypatch, capsys, only, expected):
    """benchmarks.speed --only: half of the script (the GPU run used `--only ensembles`)."""
    module = benchmark_script("speed")
    ran = []
    monkeypatch.setattr(module, "fixture_figures", lambda args: ran.append("fixtures"))
    monkeypatch.setattr(module, "ensemble_section", lambda args: ran.append("ensembles"))
    argv = ["speed.py"] + ([] if only is None else ["--only", only])
    monkeypatch.setattr(sys, "argv", argv)
    module.main()
    assert ran == expected
    monkeypatch.setattr(sys, "argv", ["speed.py", "--only", "everything"])
    with pytest.raises(SystemExit):
        module.main()
    assert "invalid choice: 'everything'" in capsys.readouterr().err


@pytest.mark.long  # about 45 s; `make test-long` runs it, CI does not
def test_long_runs_script_reports_steps_restarts_and_energy(tmp_path, capsys, monkeypatch):
    """benchmarks.long_runs: a tiny oscillator run, with and without the restart switch,
    in one solve and in chunks resumed from a checkpoint."""
    module = benchmark_script("long_runs")
    run = ["harmonic_oscillator", "0.1", "5", "6", "6", "fast", "--no-restart"]
    module.main(run)
    whole = capsys.readouterr().out
    assert "ok True, steps done 5, restarts 0" in whole
    assert "max relative energy error" in whole
    # --chunks: a run stopped after two chunks and carried on from its checkpoint prints the
    # same energy figures as the one solve
    checkpoint = str(tmp_path / "run.npz")
    module.main(run + ["--chunks", "5", "--checkpoint", checkpoint, "--chunks-now", "2"])
    out = capsys.readouterr().out
    assert "chunk 2/5" in out and "chunk 3/5" not in out
    # one step per chunk, each seeded by a fresh fit (a width-6 network on 6 nodes refits
    # too loosely for `refit_tolerance`)
    chunk_lines = [line for line in out.splitlines() if line.startswith("chunk ")]
    assert chunk_lines[0].startswith("chunk 1/5: t = 0.1, ok True, steps done 1,")
    assert all(", mean iterations " in line and line.endswith("seeded by a fresh fit 1")
               for line in chunk_lines)
    assert "stopped after 2 of 5 chunks" in out and "steps done 2," in out
    module.main(run + ["--chunks", "5", "--checkpoint", checkpoint])
    out = capsys.readouterr().out
    assert "2 of 5 chunks done" in out and "chunk 3/5" in out and "chunk 5/5" in out
    assert "ok True, steps done 5, restarts 0" in out
    lines = [[line.split("error")[-1] for line in text.splitlines() if "energy error" in line]
             for text in (out, whole)]
    assert lines[0] == lines[1] and len(lines[0]) == 2
    module.main(run + ["--chunks", "5", "--checkpoint", checkpoint, "--chunks-now", "0"])
    out = capsys.readouterr().out  # reports the checkpoint without running a chunk
    assert "5 of 5 chunks done" in out and "chunk 1/5" not in out
    assert [line.split("error")[-1] for line in out.splitlines() if "energy error" in line] \
        == lines[1]
    with pytest.raises(SystemExit, match="different run"):
        module.main(["harmonic_oscillator", "0.2", "5", "6", "6", "fast", "--no-restart",
                     "--chunks", "5", "--checkpoint", checkpoint])
    # an edited configuration is noticed too
    monkeypatch.setitem(module.CONFIGS, "fast", dict(
        module.FAST, seed=dvi.SeedPolicy(reuse_neurons=True, refit_iterations=12)))
    with pytest.raises(SystemExit, match="different run"):
        module.main(run + ["--chunks", "5", "--checkpoint", checkpoint])
    monkeypatch.undo()
    for bad in (["--chunks", "3"], ["--checkpoint", checkpoint], ["--chunks", "5", "--again"],
                ["--chunks", "5", "--chunks-now", "1"],
                ["--chunks", "5", "--checkpoint", checkpoint, "--chunks-now", "-1"]):
        with pytest.raises(SystemExit):
            module.main(run + bad)
    module.main(["harmonic_oscillator", "3.0", "4", "10", "8", "fwd", "--retry"])
    out = capsys.readouterr().out
    assert "ok True, steps done" in out and "failed trials retried in pieces" in out
    assert "retried in pieces 0," not in out  # h = 3 fails at the first step without it
    tenths = module.per_tenth(np.array([0.5, 1.0, 9.5]), np.array([1.0, 3.0, 2.0]), 0.0, 10.0)
    assert tenths[0] == 3.0 and tenths[9] == 2.0 and np.isnan(tenths[5])


def test_seed_substeps_script_prints_a_row_per_rule_and_substep_count(capsys):
    """benchmarks.seed_substeps: a tiny oscillator run converges and reports iterations."""
    module = benchmark_script("seed_substeps")
    module.main(["--problems", "harmonic_oscillator", "--rules", "early stop", "--substeps",
                 "10", "--steps", "3", "--repeats", "1"])
    rows = [[c.strip() for c in line.split("|")[1:-1]]
            for line in capsys.readouterr().out.splitlines() if "harmonic_oscillator" in line]
    ((fixture, rule, substeps, ok, median, mean, error, ms),) = rows
    assert fixture.endswith("3 steps") and rule == "early stop" and substeps == "10"
    assert ok == "True" and 1 <= int(median) <= 10 and float(error) < 1e-8 and float(ms) > 0


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


def test_root_continuation_script_follows_a_short_root_to_a_longer_step():
    """benchmarks.root_continuation: from h = 0.05 the pendulum's first-step root is followed
    to h = 1, every accepted solve a root with the error of a short step, and the lengths
    grow; a start beyond the target is refused."""
    module = benchmark_script("root_continuation")
    rows, reached, solves = module.follow("pendulum", "tanh", 1.0, lengths=6)
    assert reached == 1.0 and solves >= len(rows) + 1
    hs = [h for h, *_ in rows]
    assert hs == sorted(hs) and hs[-1] == 1.0
    assert all(residual < 1e-12 and error < 1e-6 for _, _, residual, error in rows)
    with pytest.raises(SystemExit):
        module.main(["pendulum", "tanh", "--start", "2", "--target", "1"])


def test_root_continuation_random_starts_find_the_pendulums_one_root_at_dt_10():
    """benchmarks.root_continuation --random-starts: at h = 10 some of 16 random curves reach
    the pendulum's root (two thirds of 256 did), all of them the same one, and it is the
    coarse step's root (0.38 off the motion, as continuation found); `distinct` keeps
    points apart by more than its tolerance only."""
    module = benchmark_script("root_continuation")
    ok, n, residual, q_end, p_end = module.random_starts("pendulum", "tanh", 10.0, 16)
    assert 4 <= ok.sum() < 16 and np.all(n[ok] <= 1000) and np.all(residual[ok] < 1e-10)
    roots = module.distinct(np.concatenate([q_end[ok], p_end[ok]], axis=1))
    assert len(roots) == 1
    from diffrax_vi.bench.stability import PROBLEMS

    problem = PROBLEMS["pendulum"](dtype=np.float64)
    q_ref = problem.reference(np.array([problem.t0 + 10.0]))[0][0]
    scale = 1.0 + float(np.max(np.abs(np.asarray(problem.y0[0]))))
    assert 0.3 < np.max(np.abs(roots[0][: q_ref.shape[0]] - q_ref)) / scale < 0.5
    points = np.array([[0.0, 1.0], [0.0, 1.0 + 1e-9], [0.0, 1.0 + 1e-6]])
    assert len(module.distinct(points)) == 2
    with pytest.raises(SystemExit):
        module.main(["pendulum", "tanh", "--random-starts", "-1"])


def test_pendulum_constraint_script_measures_p2_and_projects_it():
    """benchmarks.pendulum_constraint: its compiled step loop carries p₂ (nonzero after a
    network step), and the projection sets it to zero after every step."""
    import jax.numpy as jnp

    from diffrax_vi import problems

    module = benchmark_script("pendulum_constraint")
    problem = problems.pendulum(dtype=jnp.float64)
    solver = module.network(8)
    q, p, ok, residual = module.run_steps(solver, problem, 0.1, 3)
    assert ok.all() and q.shape == (3, 2) and np.all(np.abs(p[:, 1]) > 0)
    assert np.all(residual < 1e-8)
    q, p, ok, _ = module.run_steps(solver, problem, 0.1, 3, "both")
    assert ok.all() and np.all(p[:, 1] == 0)
    assert module.energy_error(problem, q, p, ok) < 1e-4
    assert module.first_failure(np.array([True, False, False])) == 2
    assert module.first_failure(np.array([True, True])) is None


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


@pytest.mark.long  # 40 s of compiling; a benchmark script, kept out of CI's time budget
def test_compile_phases_script_splits_the_first_call():
    """benchmarks.compile_phases on the smallest fixture: both phases timed, the program
    sized."""
    module = benchmark_script("compile_phases")
    trace, compile_s, size = module.phases("harmonic_oscillator", "fast", steps=2)
    assert trace > 0 and compile_s > 0 and size > 10_000
    # --cache: a second process reads the program from the persistent cache the first wrote
    first, second = module.cached_first_calls("harmonic_oscillator", "fast", 2, steps=2)
    assert 0 < second < first
    # --fresh: each process compiles the program itself (no cache between them)
    fresh = module.cached_first_calls("harmonic_oscillator", "fast", 2, steps=2, cache=False)
    assert min(fresh) > second


def test_program_parts_script_attributes_operations_to_package_functions():
    """benchmarks.program_parts: every primitive of a traced solve is counted once, the
    root finder and the residual are among the owners, and the top-level view sums the same."""
    module = benchmark_script("program_parts")
    inner = module.program_parts("harmonic_oscillator", "fast", steps=2)
    top = module.program_parts("harmonic_oscillator", "fast", depth=1, steps=2)
    assert sum(inner.values()) == sum(top.values()) > 1000
    assert any(k.startswith("nonlinear:") for k in inner)
    assert "solver:NetworkVI._step" in top and "nonlinear:AbstractDampedNewton.step" in top


def test_energy_drift_script_reports_slope_and_accepted_residuals(capsys):
    """benchmarks.energy_drift: the compiled step loop returns states and accepted
    residuals, and the summary recovers a known linear drift; the adaptive peer run that it
    shares with `benchmarks.long_runs` (`benchmarks.common`)."""
    import jax.numpy as jnp

    from benchmarks.common import peer_run
    from diffrax_vi import problems

    module = benchmark_script("energy_drift")
    problem = problems.harmonic_oscillator(dtype=jnp.float64)
    q, p, ok, residual, refits, steady, iterations = module.run_steps(
        module.solver_for("default"), problem, 0.25, 5, repeats=1)
    assert ok.all() and q.shape == (5, 1) and np.all((residual > 0) & (residual < 1e-8))
    # the projected default solves the oscillator's linear step equations in one iteration
    assert refits == 0 and steady > 0 and iterations == 1
    summary = module.drift_summary(problem, q, p, residual)
    assert summary["residual"][2] == residual.max() and len(summary["windows"]) == 5
    assert summary["windows"][-1] < 1e-8
    # an adaptive peer over the same span, energy sampled along it
    largest, accepted, seconds, ok = peer_run("dopri8", 1e-8, problem, 0.25, 5, 4)
    assert ok and 0 < largest < 1e-6 and accepted > 0 and seconds > 0

    class Drifting:  # energy rises by 1e-9 of E₀ per step
        t0 = 0.0
        y0 = (jnp.zeros(1), jnp.ones(1))

        def energy(self, t, q, p):
            return 1.0 + 1e-9 * q[0]

    steps = np.arange(1.0, 21.0)[:, None]
    summary = module.drift_summary(Drifting(), steps, np.ones_like(steps), np.full(20, 1e-12))
    assert summary["slope"] == pytest.approx(1e-9, rel=1e-6)
    assert summary["change"][0] == pytest.approx(1e-9, rel=1e-6)
    # a mistyped peer is refused before anything runs, with the known names
    for bad, words in (("tsit6:1e-10", "unknown peer 'tsit6'"), ("dopri8", "positive RTOL"),
                       ("dopri8:x", "positive RTOL")):
        with pytest.raises(SystemExit):
            module.main(["harmonic_oscillator", "0.25", "5", "--configs", "cgvi", "--peers", bad])
        assert words in capsys.readouterr().err


def test_oga_coordinates_script_compares_loop_and_vmap():
    """benchmarks.oga_coordinates: both layouts of the per-coordinate OGA seed give the
    same parameters, and both are timed."""
    module = benchmark_script("oga_coordinates")
    r = module.compare(2, repeats=1, dict_amount=200)
    assert r["diff"] <= 1e-10
    assert min(r["loop"] + r["vmap"]) > 0


def test_floor_acceptance_script_solves_a_fixture_and_refuses_bad_settings(capsys):
    """benchmarks.floor_acceptance: a fixture row under a root-finder setting and a patched
    tolerance; malformed settings are refused by name."""
    import diffrax_vi.nonlinear as nonlinear

    module = benchmark_script("floor_acceptance")
    original = nonlinear.default_tolerances
    try:
        module.main(["--only", "1", "--root-finder", "lam=1e-3", "--tolerance", "otol_slow=0.75"])
        eps = float(np.finfo(np.float64).eps)
        assert nonlinear.default_tolerances(jnp.float64)["otol_slow"] == eps**0.75
    finally:
        nonlinear.default_tolerances = original
    row = [line for line in capsys.readouterr().out.splitlines() if "relu_k(3) 4" in line]
    assert len(row) == 1 and "| True |" in row[0]
    error = float(row[0].split("|")[3])
    assert 0 < error <= 1e-12  # test_solver: measured 3.8e-13
    for argv, message in (
        (["--root-finder", "lam"], "expected NAME=VALUE"),
        (["--root-finder", "lam=small"], "not a Python literal"),
        (["--root-finder", "damping=1"], "--root-finder"),
        (["--tolerance", "floor_movin=0.7"], "unknown tolerance"),
    ):
        with pytest.raises(SystemExit, match=message):
            module.main(argv)
    assert nonlinear.default_tolerances is original


def test_step_structure_script_reports_the_three_spectra(tmp_path, capsys):
    """benchmarks.step_structure --tiny: one converged oscillator step (tanh 6, GL8) with the
    ranks of the tangent data (18 x 18), the step Jacobian (19 x 19) and the hidden features
    (18 x 6) written to --out; a refused combination gets its row without a solve."""
    module = benchmark_script("step_structure")
    out = tmp_path / "structure.txt"
    module.main(["--tiny", "--out", str(out)])
    module.main(["--tiny", "--widths", "16", "--nodes", "4", "--out", str(out), "--append"])
    capsys.readouterr()
    rows = [[c.strip() for c in line.split("|")[1:-1]]
            for line in out.read_text().splitlines() if line.startswith("| ho0.1 |")]
    (ok, refused) = rows
    assert ok[:5] == ["ho0.1", "tanh", "6", "8", "ok"] and 1 <= int(ok[5]) <= 50
    assert ok[7] == "18x18" and ok[12] == "19" and ok[16] == "18x6"
    a8, a13, b8, b13 = int(ok[8]), int(ok[9]), int(ok[13]), int(ok[14])
    assert 0 < a8 <= a13 <= 18 and 0 < b8 <= b13 <= 19
    # measured: the six hidden features are independent at 1e-11 (ranks 6, 6, 6)
    assert [int(x) for x in ok[17:20]] == [6, 6, 6] and ok[20] == "yes"
    assert refused[4] == "refused" and set(refused[5:]) == {"–"}
    with pytest.raises(SystemExit):
        module.main(["--tiny", "--activations", "relu", "--out", "-"])


@pytest.mark.long
def test_projection_script_energy_section(capsys):
    """benchmarks.projection --sections energy: a 20-step oscillator run per solver, with
    every solver's row successful and an energy error at the level of a converged step."""
    module = benchmark_script("projection")
    module.main(["--sections", "energy", "--energy-steps", "20"])
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 20 |")]
    assert len(rows) == 3
    for row in rows:
        cells = [c.strip() for c in row.split("|")[1:-1]]
        assert cells[2] == "ok"
        assert float(cells[3]) <= 1e-10
    with pytest.raises(SystemExit):
        module.main(["--sections", "nothing"])
