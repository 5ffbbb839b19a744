"""Where a sweep's cases run: in this process, or on the workers of a Dask cluster.

A sweep is a list of cases plus a `Sweep` object that knows how to name a case (a stable id),
which cases share one compiled program (its configuration key), and how to run the cases of one
configuration. `run_sweep` groups the cases into batches of one configuration each, hands the
batches to an executor and appends every finished case to a `ResultLog` (one JSON line per
case, written with one `write` and an `fsync`), so that a sweep stopped part way resumes where
it stopped and no finished case is computed twice.

Executors:

- `SerialExecutor`: the batches one after another in this process.
- `DaskExecutor`: the batches as tasks on a Dask cluster: an existing one (`scheduler=` its
  address) or an embedded `LocalCluster` of one single-threaded worker process per CPU, each
  pinned to its own CPUs. A worker keeps its compiled solves between batches; it streams each
  finished case back to the client as soon as it has it; when a worker dies, Dask hands its
  batch to another worker, and cases that had already arrived are not logged again.

Dask (`pip install diffrax_vi[distributed]`) is imported only by `DaskExecutor`.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable, Hashable, Iterable, Sequence
from typing import Any, Protocol, runtime_checkable

__all__ = [
    "Sweep",
    "ResultLog",
    "SerialExecutor",
    "DaskExecutor",
    "SweepIncomplete",
    "run_sweep",
    "cpu_slots",
    "QUIET_WORKERS",
]

Rows = list[dict[str, Any]]
Emit = Callable[[str, Rows], None]


@runtime_checkable
class Sweep(Protocol):
    """What an executor needs to know about a kind of case. A sweep object travels to the
    workers, so it must pickle (plain settings, no compiled functions).

    - `name`: labels the worker-side cache of compiled solves.
    - `case_id(case)`: a stable string naming the case (the log's key).
    - `config_key(case)`: cases with equal keys share one compiled program and run together.
    - `run(cases, cache, emit)`: runs cases of one configuration, calling `emit(case_id, rows)`
      as each finishes (a case may have several rows, or none); `cache` is a dict that lives
      as long as the worker, for the compiled solves.
    """

    name: str

    def case_id(self, case: Any) -> str: ...

    def config_key(self, case: Any) -> Hashable: ...

    def run(self, cases: Sequence[Any], cache: dict, emit: Emit) -> None: ...


class SweepIncomplete(RuntimeError):
    """Some batches failed on the executor (not a case's own failure, which is a row): the
    finished cases are in the log, and a run with `resume=True` does the rest."""

    def __init__(self, missing: Sequence[str], errors: Sequence[str]):
        self.missing = list(missing)
        self.errors = list(errors)
        super().__init__(
            f"{len(self.missing)} case(s) did not finish ({'; '.join(self.errors[:3])}); "
            "the finished ones are logged: run again with resume to complete the sweep"
        )


# -- the log ------------------------------------------------------------------------------------
def _plain(x: Any) -> Any:
    """NumPy scalars and arrays as JSON values."""
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"cannot write a {type(x).__name__} to the result log")


class ResultLog:
    """One JSON line per finished case, `{"case": id, "rows": [...]}`, in a file that is only
    ever appended to. Each line is written with a single `os.write` on a file opened with
    `O_APPEND`, then `fsync`-ed: a reader sees whole lines, and a line torn by a crash (the
    last one, without its newline) is cut off before the next append.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)

    def reset(self) -> None:
        """Start an empty log (a fresh sweep)."""
        os.makedirs(os.path.dirname(self.path) or ".", exist_ok=True)
        with open(self.path, "w"):
            pass

    def load(self) -> dict[str, Rows]:
        """The finished cases, by id (empty when there is no log). Repairs a torn last line."""
        if not os.path.exists(self.path):
            return {}
        with open(self.path, "rb") as f:
            data = f.read()
        end = data.rfind(b"\n") + 1
        if end < len(data):  # an interrupted write: drop the partial line
            with open(self.path, "r+b") as f:
                f.truncate(end)
        done: dict[str, Rows] = {}
        for number, line in enumerate(data[:end].splitlines(), start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
                done[record["case"]] = record["rows"]
            except (ValueError, KeyError, TypeError) as e:
                raise ValueError(f"{self.path}:{number}: not a result-log line ({e})") from None
        return done

    def append(self, case_id: str, rows: Rows) -> None:
        """Append one finished case, durably."""
        line = json.dumps({"case": case_id, "rows": rows}, default=_plain) + "\n"
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line.encode())
            os.fsync(fd)
        finally:
            os.close(fd)


# -- running the batches ------------------------------------------------------------------------

# Compiled solves of this process, per sweep name: on a Dask worker they outlive a batch.
_CACHES: dict[str, dict] = {}


def _jax_settings() -> dict[str, Any]:
    """The JAX settings a worker copies from the client (float64 is the caller's choice)."""
    import jax

    return {"jax_enable_x64": bool(jax.config.jax_enable_x64)}


def _run_batch(sweep: Sweep, cases: Sequence[Any], settings: dict[str, Any],
               queue_name: str | None = None) -> list[tuple[str, Rows]]:
    """A batch on a worker: run its cases with the worker's cache, publish each to the
    client's queue as it finishes, and return them all (in case a message was lost)."""
    import jax

    for name, value in settings.items():
        jax.config.update(name, value)
    out: list[tuple[str, Rows]] = []
    sink = None
    if queue_name is not None:
        from distributed import Queue

        sink = Queue(queue_name)

    def emit(case_id: str, rows: Rows) -> None:
        if sink is not None:
            sink.put((case_id, rows))
        out.append((case_id, rows))

    sweep.run(cases, _CACHES.setdefault(sweep.name, {}), emit)
    return out


class SerialExecutor:
    """The batches one after another in this process (no Dask)."""

    workers = 1

    def run(self, sweep: Sweep, batches: Sequence[Sequence[Any]], emit: Emit) -> list[str]:
        cache = _CACHES.setdefault(sweep.name, {})
        errors = []
        for batch in batches:
            try:
                sweep.run(batch, cache, emit)
            except Exception as e:  # as on a cluster: the other batches still run
                errors.append(f"{type(e).__name__}: {e}")
        return errors

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def cpu_slots(jobs: int) -> list[set[int] | None]:
    """One set of CPUs per worker, disjoint where the machine has enough of them.

    Each XLA process sizes its thread pools to the CPUs it may run on, and its threads spin
    while they wait: two unpinned processes on the same cores slow each other down badly.
    `None` leaves a worker unpinned (no CPU affinity here, or fewer CPUs than workers)."""
    if not hasattr(os, "sched_getaffinity"):
        return [None] * jobs
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < jobs:
        return [None] * jobs
    return [set(cpus[k::jobs]) for k in range(jobs)]


def _pin_process(cpus: set[int]) -> None:
    """Restrict every thread of this process (and so the threads it starts later) to `cpus`."""
    try:
        threads = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        threads = [0]
    for tid in threads:
        try:
            os.sched_setaffinity(tid, cpus)
        except OSError:  # a thread that ended meanwhile
            pass


def _pin_plugin(slots: list[set[int] | None]):
    """A Dask worker plugin that pins worker `k` of a `LocalCluster` to `slots[k]`."""
    from distributed import WorkerPlugin

    class PinCPUs(WorkerPlugin):
        name = "diffrax-vi-pin-cpus"

        def setup(self, worker):
            try:
                index = int(worker.name)
            except (TypeError, ValueError):
                return
            cpus = slots[index % len(slots)]
            if cpus is not None:
                _pin_process(cpus)

    return PinCPUs()


def _import_distributed():
    try:
        import distributed
    except ImportError as e:
        raise ImportError(
            "running a sweep on Dask needs the `distributed` package: "
            "pip install 'diffrax_vi[distributed]'"
        ) from e
    return distributed


# Settings of the embedded cluster. A worker's event loop shares its one CPU with the
# computation, so what it does on a timer is taken from the cases: with Dask's defaults
# (profiler samples every 10 ms, the loop's tick every 20 ms, the nanny's memory check every
# 100 ms, system metrics every 500 ms) the cases ran measurably slower on a pinned worker
# than in a pinned process (the benchmarks page, "Sweeps on a Dask cluster"). The profiler
# and the metrics feed a dashboard this cluster does not have.
QUIET_WORKERS = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "10s",
    "distributed.worker.memory.monitor-interval": "1s",
}


class DaskExecutor:
    """The batches as tasks on a Dask cluster.

    **Arguments:**

    - `scheduler`: the address of a running scheduler (`"tcp://host:8786"`), or a
      `distributed.Client` already connected; `None` (default) starts an embedded
      `LocalCluster` that lives as long as this executor, its workers configured with
      `QUIET_WORKERS` (slow timers, no profiler).
    - `workers`: worker processes of the embedded cluster (default: one per CPU this
      process may use). Each has one thread and, where the machine has a CPU for each, its
      own CPUs.
    - `timeout`: seconds to wait for a scheduler (and for the embedded cluster to start).

    Raises `ConnectionError` naming the address when no scheduler answers there.
    """

    def __init__(self, scheduler: Any = None, *, workers: int | None = None,
                 timeout: float = 30.0):
        distributed = _import_distributed()
        self._cluster = None
        self._own_client = True
        if workers is not None and (not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be a positive integer, got {workers!r}")
        if isinstance(scheduler, distributed.Client):
            self.client = scheduler
            self._own_client = False
        elif scheduler is not None:
            if workers is not None:
                raise ValueError("workers sizes the embedded cluster; a scheduler has its own")
            try:
                self.client = distributed.Client(scheduler, timeout=timeout)
            except (OSError, TimeoutError) as e:
                raise ConnectionError(
                    f"no Dask scheduler answered at {scheduler!r} within {timeout:g} s ({e})"
                ) from None
        else:
            if workers is None:
                workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
                    else (os.cpu_count() or 1)
            import dask

            with dask.config.set(QUIET_WORKERS):
                self._cluster = distributed.LocalCluster(
                    n_workers=workers, threads_per_worker=1, processes=True,
                    dashboard_address=None, silence_logs=40, timeout=timeout,
                )
            self.client = distributed.Client(self._cluster, timeout=timeout)
            self.client.register_plugin(_pin_plugin(cpu_slots(workers)))

    @property
    def workers(self) -> int:
        """Workers connected now."""
        return len(self.client.scheduler_info(n_workers=-1)["workers"])

    def run(self, sweep: Sweep, batches: Sequence[Sequence[Any]], emit: Emit) -> list[str]:
        """Submit every batch, emit each case as it arrives; return the errors of the batches
        that failed on the cluster (their unfinished cases are then missing)."""
        from distributed import Queue

        if not batches:
            return []
        settings = _jax_settings()
        arrivals = Queue(client=self.client)
        futures = [
            self.client.submit(_run_batch, sweep, list(batch), settings, arrivals.name,
                               pure=False, key=f"{sweep.name}-batch-{k}-{os.urandom(4).hex()}")
            for k, batch in enumerate(batches)
        ]
        pending = set(futures)
        errors: list[str] = []

        def drain() -> None:
            for case_id, rows in arrivals.get(batch=True):  # what is there, without waiting
                emit(case_id, rows)

        try:
            while pending:
                time.sleep(0.1)
                drain()
                for future in [f for f in pending if f.done()]:
                    pending.discard(future)
                    try:
                        results = future.result()
                    except Exception as e:  # e.g. KilledWorker, after Dask's retries
                        errors.append(f"{type(e).__name__}: {e}")
                        continue
                    for case_id, rows in results:
                        emit(case_id, rows)
            drain()
        finally:
            for future in pending:
                future.cancel()
            arrivals.close()
        return errors

    def close(self) -> None:
        """Close the client, and the embedded cluster if there is one."""
        if self._own_client:
            self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# -- the sweep ----------------------------------------------------------------------------------
def _batches(sweep: Sweep, cases: Sequence[Any], size: int | None) -> list[list[Any]]:
    """The cases grouped by configuration (first appearance first), each group split into
    batches of at most `size` cases."""
    groups: dict[Hashable, list[Any]] = {}
    for case in cases:
        groups.setdefault(sweep.config_key(case), []).append(case)
    out = []
    for group in groups.values():
        step = len(group) if size is None else size
        out += [group[k:k + step] for k in range(0, len(group), step)]
    return out


def run_sweep(
    sweep: Sweep,
    cases: Iterable[Any],
    *,
    executor: Any = None,
    log: str | os.PathLike | ResultLog | None = None,
    resume: bool = False,
    progress: Any = None,
    batch_size: int | None = None,
    on_case: Emit | None = None,
) -> Rows:
    """Run every case once and return their rows, in the order of `cases`.

    **Arguments:**

    - `sweep`: the kind of case, an object with `name`, `case_id(case)` (a stable string),
      `config_key(case)` (equal keys share one compiled program) and `run(cases, cache,
      emit)` (see `Sweep`); it must pickle, to travel to the workers.
    - `cases`: the cases; their ids must be distinct.
    - `executor`: a `SerialExecutor` (default), a `DaskExecutor`, or any object whose
      `run(sweep, batches, emit)` runs lists of cases and returns the errors of those that
      failed.
    - `log`: a path (or `ResultLog`) that every finished case is appended to as it arrives.
    - `resume`: keep the cases already in `log` and run only the others; otherwise the log is
      started afresh.
    - `progress`: a tqdm-like object (`update(n)`), advanced once per case.
    - `batch_size`: the most cases of one configuration in one task (default: all of them;
      smaller batches spread one configuration over several workers, each compiling it).
    - `on_case`: called with `(case_id, rows)` as each new case is logged.

    Raises `SweepIncomplete` when batches failed on the executor; the finished cases are in
    the log by then.
    """
    cases = list(cases)
    if not isinstance(sweep, Sweep):
        raise TypeError(f"sweep must provide name, case_id, config_key and run; got {sweep!r}")
    if batch_size is not None and (not isinstance(batch_size, int) or batch_size < 1):
        raise ValueError(f"batch_size must be None or a positive integer, got {batch_size!r}")
    ids = [sweep.case_id(c) for c in cases]
    if len(set(ids)) != len(ids):
        seen: set[str] = set()
        twice = next(i for i in ids if i in seen or seen.add(i))
        raise ValueError(f"the sweep holds case {twice!r} more than once")
    if log is not None and not isinstance(log, ResultLog):
        log = ResultLog(log)
    done: dict[str, Rows] = {}
    if log is not None:
        if resume:
            wanted = set(ids)
            done = {k: v for k, v in log.load().items() if k in wanted}
        else:
            log.reset()
    if progress is not None and done:
        progress.update(len(done))
    todo = [c for c, i in zip(cases, ids, strict=True) if i not in done]
    lock = threading.Lock()

    def emit(case_id: str, rows: Rows) -> None:
        with lock:
            if case_id in done:  # a batch run again after its worker died
                return
            done[case_id] = rows
            if log is not None:
                log.append(case_id, rows)
        if on_case is not None:
            on_case(case_id, rows)
        if progress is not None:
            progress.update(1)

    executor = SerialExecutor() if executor is None else executor
    errors = executor.run(sweep, _batches(sweep, todo, batch_size), emit)
    missing = [i for i in ids if i not in done]
    if missing:
        raise SweepIncomplete(missing, errors or ["no result returned"])
    return [row for i in ids for row in done[i]]

