"""The sweep executor (`diffrax_vi.bench.executor`): a sweep on a two-worker Dask
`LocalCluster` gives the serial run's rows, survives a killed worker with every case once,
and a resumed sweep ends with the uninterrupted table without recomputing a finished case."""

from __future__ import annotations

import json
import os
import signal
import socket
import sys
import time

import cloudpickle
import pytest

from diffrax_vi.bench import stability
from diffrax_vi.bench.executor import (
    DaskExecutor,
    ResultLog,
    SerialExecutor,
    SweepIncomplete,
    run_sweep,
)
from diffrax_vi.bench.stability import StabilitySweep, quick_grid, stability_sweep

# The fake sweeps below are defined here; workers cannot import this file, so they travel by
# value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])

# A few cases of the quick stability sweep: the oscillator's tanh network in float64,
# Levenberg-Marquardt, our convergence test, every dt, constant steps only (one compilation:
# CI time is short).
CASES = quick_grid(["harmonic_oscillator"], dtypes=("float64",), activations=("tanh",),
                   solvers=("LevenbergMarquardt",), acceptances=("strict",), retry_dts=(),
                   pid_dts=())
COMPARED = ("status", "iterations", "steps_done", "ref_err", "ham_drift")


def _table(rows):
    return [(r["dtype"], r["dt"], *(r.get(k) for k in COMPARED)) for r in rows]


@pytest.fixture(scope="module")
def serial_rows():
    return stability_sweep(CASES)


@pytest.fixture(scope="module")
def cluster():
    with DaskExecutor(workers=2) as executor:
        yield executor


def test_the_cases_see_both_outcomes(serial_rows):
    assert len(CASES) == 3 and len({c.solver_key() for c in CASES}) == 1
    statuses = [r["status"] for r in serial_rows]
    assert statuses == ["ok", "ok", "diverged"]  # the comparison below sees both kinds
    assert len({r["iterations"] for r in serial_rows}) == 3


def test_embedded_workers_keep_their_timers_slow_and_their_profiler_off(cluster):
    """A worker's timers share its one CPU with the cases: the embedded cluster slows the
    event loop's tick, the memory and system monitors, and turns the profiler off."""
    from dask.utils import parse_timedelta

    from diffrax_vi.bench.executor import QUIET_WORKERS

    def timers(dask_worker):
        import dask

        return ({name: pc.callback_time for name, pc in dask_worker.periodic_callbacks.items()},
                dask.config.get("distributed.worker.profile.enabled"))

    ms = {key: 1000 * parse_timedelta(value) for key, value in QUIET_WORKERS.items()
          if isinstance(value, str)}
    per_worker = cluster.client.run(timers)
    assert len(per_worker) == 2
    for callbacks, profiling in per_worker.values():
        assert profiling is False
        assert callbacks["tick"] == ms["distributed.admin.tick.interval"] >= 1000
        assert callbacks["monitor"] == ms["distributed.admin.system-monitor.interval"] >= 10_000
        assert callbacks["memory_monitor"] == ms["distributed.worker.memory.monitor-interval"]
        assert "profile" not in callbacks


def test_local_cluster_sweep_matches_the_serial_run(cluster, serial_rows, tmp_path):
    assert cluster.workers == 2
    log = tmp_path / "stability.jsonl"
    # batches of two cases: both workers get one (and each compiles the configuration)
    rows = stability_sweep(CASES, executor=cluster, log=str(log), batch_size=2)
    # case by case: the same statuses, iteration counts, errors and drifts
    assert _table(rows) == _table(serial_rows)
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    assert sorted(x["case"] for x in lines) == sorted(StabilitySweep().case_id(c) for c in CASES)


class _SlowSweep:
    """Cases `(config, k)` that sleep and report the process that ran them."""

    name = "test-slow"

    def case_id(self, case):
        return f"{case[0]}-{case[1]}"

    def config_key(self, case):
        return case[0]

    def run(self, cases, cache, emit):
        for case in cases:
            time.sleep(0.4)
            emit(self.case_id(case), [{"config": case[0], "k": case[1], "pid": os.getpid()}])


def test_a_killed_worker_has_its_batch_rerun_and_every_case_lands_once(cluster, tmp_path):
    cases = [(config, k) for config in ("a", "b") for k in range(5)]
    killed = []

    def kill_first_worker(case_id, rows):
        if not killed:  # its batch is part way: one case in, four to go
            killed.append(rows[0])
            os.kill(rows[0]["pid"], signal.SIGKILL)

    log = tmp_path / "slow.jsonl"
    rows = run_sweep(_SlowSweep(), cases, executor=cluster, log=str(log),
                     on_case=kill_first_worker)
    assert [(r["config"], r["k"]) for r in rows] == cases
    ids = [json.loads(x)["case"] for x in log.read_text().splitlines()]
    assert sorted(ids) == sorted(f"{c}-{k}" for c, k in cases)  # each case once
    (first,) = killed
    again = [r for r in rows if r["config"] == first["config"]]
    assert again[first["k"]]["pid"] == first["pid"]  # the case that had arrived is kept
    assert any(r["pid"] != first["pid"] for r in again)  # the rest ran elsewhere
    assert cluster.workers >= 1


class _Interrupt(KeyboardInterrupt):
    pass


def test_a_resumed_sweep_ends_with_the_same_table_and_recomputes_nothing(
        serial_rows, tmp_path, monkeypatch):
    log = tmp_path / "stability.jsonl"
    sweep = StabilitySweep()
    cases = sorted(CASES, key=lambda c: (repr(c.solver_key()), c.acceptance, c.dt))

    def stop_after_two(case_id, rows):
        if len(log.read_text().splitlines()) == 2:
            raise _Interrupt

    with pytest.raises(_Interrupt):
        run_sweep(sweep, cases, log=str(log), on_case=stop_after_two)
    finished = set(ResultLog(log).load())
    assert len(finished) == 2
    ran = []
    real = stability.run_case
    monkeypatch.setattr(stability, "run_case", lambda case, cache: ran.append(case)
                        or real(case, cache))
    rows = stability_sweep(CASES, log=str(log), resume=True)
    assert _table(rows) == _table(serial_rows)
    assert len(ran) == 1 and not {sweep.case_id(c) for c in ran} & finished
    assert len(ResultLog(log).load()) == len(CASES)


def test_result_log_keeps_whole_lines_and_cuts_a_torn_one(tmp_path):
    log = ResultLog(tmp_path / "sub" / "log.jsonl")
    log.reset()
    log.append("a", [{"x": 1.5, "y": None}])
    log.append("b", [])
    with open(log.path, "a") as f:
        f.write('{"case": "c", "ro')  # a write cut short by a crash
    assert log.load() == {"a": [{"x": 1.5, "y": None}], "b": []}
    log.append("c", [{"x": float("inf")}])
    assert log.load()["c"] == [{"x": float("inf")}]
    with open(log.path, "a") as f:
        f.write("not json\n")
    with pytest.raises(ValueError, match="log.jsonl:4: not a result-log line"):
        log.load()


class _Broken:
    name = "test-broken"

    def case_id(self, case):
        return str(case)

    def config_key(self, case):
        return case % 2

    def run(self, cases, cache, emit):
        for case in cases:
            if case == 3:
                raise RuntimeError("no luck")
            emit(str(case), [{"case": case}])


def test_run_sweep_refuses_duplicates_and_reports_failed_batches(tmp_path):
    with pytest.raises(ValueError, match="case '1' more than once"):
        run_sweep(_Broken(), [0, 1, 1])
    with pytest.raises(TypeError, match="sweep must provide"):
        run_sweep(object(), [0])
    with pytest.raises(ValueError, match="batch_size"):
        run_sweep(_Broken(), [0], batch_size=0)
    log = tmp_path / "log.jsonl"
    with pytest.raises(SweepIncomplete, match="2 case.*RuntimeError: no luck") as info:
        run_sweep(_Broken(), range(6), executor=SerialExecutor(), log=str(log))
    assert info.value.missing == ["3", "5"]
    assert set(ResultLog(log).load()) == {"0", "1", "2", "4"}  # the others are kept


def test_an_unreachable_scheduler_is_named():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    with pytest.raises(ConnectionError, match=f"no Dask scheduler answered at '{address}'"):
        DaskExecutor(address, timeout=1)
    with pytest.raises(ValueError, match="workers"):
        DaskExecutor(workers=0)


@pytest.mark.long
def test_whole_quick_stability_sweep_on_two_workers_matches_serial(tmp_path):
    """The whole quick sweep (324 cases: 216, the 72 at dt = 1 and 10 again under
    RetryFailedSteps, the 36 at dt = 10 under PIDController): the cluster's table is the
    serial one."""
    cases = quick_grid()
    serial = stability_sweep(cases)
    with DaskExecutor(workers=2) as executor:
        rows = stability_sweep(cases, executor=executor, log=str(tmp_path / "s.jsonl"))
    assert len(rows) == len(cases)
    assert _table(rows) == _table(serial)


def test_cli_resume_runs_only_the_missing_cases(tmp_path):
    """`--resume` keeps the logged cases (their measured wall times come back unchanged) and
    runs the others; the CSV is the whole table in case order."""
    from diffrax_vi.bench.__main__ import main as cli_main
    from diffrax_vi.bench.rows import read_rows

    out = str(tmp_path / "out")
    argv = ["work-precision", "--problems", "harmonic_oscillator", "pendulum", "--solvers",
            "scipy", "--repeats", "1", "--jobs", "1", "--no-progress", "--out", out]
    cli_main(argv)
    first = read_rows(os.path.join(out, "work_precision.csv"))
    log = tmp_path / "out" / "work_precision.jsonl"
    lines = log.read_text().splitlines()
    assert len(first) == len(lines) == 10
    log.write_text("\n".join(lines[:6]) + "\n")  # as if stopped after six cases
    cli_main(argv + ["--resume"])
    second = read_rows(os.path.join(out, "work_precision.csv"))
    key = [(r["problem"], r["value"]) for r in first]
    assert [(r["problem"], r["value"]) for r in second] == key
    assert [r["wall_s"] for r in second[:6]] == [r["wall_s"] for r in first[:6]]
    assert len(log.read_text().splitlines()) == 10


def test_cli_names_an_unreachable_scheduler(tmp_path, monkeypatch):
    from diffrax_vi.bench import executor
    from diffrax_vi.bench.__main__ import main as cli_main

    real = executor.DaskExecutor
    monkeypatch.setattr(executor, "DaskExecutor",
                        lambda address, workers=None: real(address, workers=workers, timeout=1))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(SystemExit, match=f"no Dask scheduler answered at 'tcp://127.0.0.1:{port}'"):
        cli_main(["work-precision", "--problems", "harmonic_oscillator", "--solvers", "scipy",
                  "--scheduler", f"tcp://127.0.0.1:{port}", "--no-progress",
                  "--out", str(tmp_path)])


@pytest.mark.long
def test_energy_sweep_gives_the_studys_rows():
    """The energy sweep has one case per run, each with its samples."""
    from diffrax_vi.bench.sweeps import EnergySweep

    sweep = EnergySweep()
    cases = sweep.cases("harmonic_oscillator", 40, [1e-8])
    assert [c.entry for c in cases][-2:] == ["Tsit5", "Dopri8"]
    seen = []
    rows = run_sweep(sweep, cases, on_case=lambda case_id, rs: seen.append(len(rs)))
    assert seen == [40] * len(cases) and all(r["status"] == "ok" for r in rows)
