"""The command line's studies as sweeps of `executor.run_sweep`: work-precision and long-time
energy (the stability sweep's is `stability.StabilitySweep`).

A case names its solver by its label, not by the object: the worker builds the entry from
`suites` itself, so that a case is a few strings and numbers that travel to any worker. A
sweep's configuration key is the set of cases that share one compiled program (one entry on
one problem), so a worker compiles it once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

from .entries import Adaptive, Entry
from .harness import long_time_energy, work_precision

__all__ = [
    "WorkPrecisionCase",
    "WorkPrecisionSweep",
    "EnergyCase",
    "EnergySweep",
    "energy_runs",
]

Emit = Callable[[str, list[dict[str, Any]]], None]


def _entry(entries: Sequence[Entry], name: str, problem: str) -> Entry:
    for entry in entries:
        if entry.name == name:
            return entry
    raise ValueError(f"{problem}: no solver entry named {name!r}; "
                     f"choose from {[e.name for e in entries]}")


# -- work-precision -----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class WorkPrecisionCase:
    """One point of the work-precision study: `entry` (a solver entry's name) on `problem` at
    `value` (steps over the span, or rtol)."""

    problem: str
    entry: str
    value: float


@dataclasses.dataclass(frozen=True)
class WorkPrecisionSweep:
    """`harness.work_precision` of the published suites (`full`: the full grids), a case per
    point; `repeats` and `budget_s` as there."""

    full: bool = False
    repeats: int = 2
    budget_s: float = 20.0
    name: str = "work-precision"

    def case_id(self, case: WorkPrecisionCase) -> str:
        return f"{case.problem}|{case.entry}|{case.value!r}"

    def config_key(self, case: WorkPrecisionCase) -> tuple:
        return (case.problem, case.entry)

    def entries(self, problem: str) -> list[Entry]:
        from .suites import SETTINGS, networkvi_entries, peer_entries

        return networkvi_entries(SETTINGS[problem], self.full) + peer_entries(self.full)

    def cases(self, problems: Sequence[str],
              keep: Callable[[str], bool] = lambda name: True) -> list[WorkPrecisionCase]:
        """Every point of `problems`, for the entries whose name `keep` accepts."""
        from .suites import sweeps

        out = []
        for problem in problems:
            entries = [e for e in self.entries(problem) if keep(e.name)]
            steps, rtols = sweeps(problem, entries, self.full)
            for entry in entries:
                values = steps.get(entry.name) or rtols.get(entry.name) or ()
                out += [WorkPrecisionCase(problem, entry.name, v) for v in values]
        return out

    def run(self, cases: Sequence[WorkPrecisionCase], cache: dict, emit: Emit) -> None:
        from .entries import Fixed
        from .suites import SETTINGS

        problem = cases[0].problem
        entry = _entry(self.entries(problem), cases[0].entry, problem)
        values = [c.value for c in cases]
        by_value = {c.value: c for c in cases}
        sweep = {"steps": {entry.name: values}} if isinstance(entry, Fixed) \
            else {"rtols": {entry.name: values}}

        def stream(rows):
            for row in rows:
                emit(self.case_id(by_value.pop(row["value"])), [row])

        work_precision(SETTINGS[problem].make(), [entry], repeats=self.repeats,
                       budget_s=self.budget_s, on_rows=stream, **sweep)
        for case in by_value.values():  # values skipped after a run that cannot work
            emit(self.case_id(case), [])


# -- long-time energy ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class EnergyCase:
    """One run of the long-time energy study: `entry` on `problem` over `steps` long steps
    (`setting.long_dt` each) at `value` (the steps for NetworkVI, an rtol for a peer)."""

    problem: str
    entry: str
    value: float
    steps: int


def energy_runs(problem: str, steps: int, retry: bool, rtols: Sequence[float]
                ) -> list[tuple[Entry, float]]:
    """`(entry, value)` of every run of the energy study on `problem`: NetworkVI's energy
    entries (stepping with `RetryFailedSteps` and " retry" in their names where `retry`) over
    `steps` steps, then Tsit5 and Dopri8 at each of `rtols`."""
    from .suites import SETTINGS, energy_entries, peer_entries

    ours = energy_entries(SETTINGS[problem])
    if retry:
        ours = [dataclasses.replace(e, name=f"{e.name} retry", retry=True) for e in ours]
    peers = [e for e in peer_entries(False)
             if isinstance(e, Adaptive) and e.name in ("Tsit5", "Dopri8")]
    return [(e, steps) for e in ours] + [(p, r) for p in peers for r in rtols]


@dataclasses.dataclass(frozen=True)
class EnergySweep:
    """`harness.long_time_energy` of the published suites, a case per run; `retry` and
    `adaptive_max_steps` as the command line's `--retry` and `--adaptive-max-steps`."""

    retry: bool = False
    adaptive_max_steps: int = 2**19
    name: str = "energy"

    def case_id(self, case: EnergyCase) -> str:
        return f"{case.problem}|{case.steps}|{case.entry}|{case.value!r}"

    def config_key(self, case: EnergyCase) -> tuple:
        return (case.problem, case.steps, case.entry)

    def cases(self, problem: str, steps: int, rtols: Sequence[float]) -> list[EnergyCase]:
        return [EnergyCase(problem, e.name, v, steps)
                for e, v in energy_runs(problem, steps, self.retry, rtols)]

    def run(self, cases: Sequence[EnergyCase], cache: dict, emit: Emit) -> None:
        from .suites import SETTINGS

        first = cases[0]
        setting = SETTINGS[first.problem]
        rtols = [c.value for c in cases]
        runs = energy_runs(first.problem, first.steps, self.retry, rtols)
        entry = _entry([e for e, _ in runs], first.entry, first.problem)
        problem = setting.make()
        problem = problem.with_span(problem.t0 + first.steps * setting.long_dt)
        pending = list(cases)

        def stream(rows):
            case = pending.pop(0)
            emit(self.case_id(case), rows)

        long_time_energy(problem, [(entry, c.value) for c in cases], on_rows=stream,
                         adaptive_max_steps=self.adaptive_max_steps)

