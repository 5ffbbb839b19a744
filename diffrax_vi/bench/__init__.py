"""Benchmark and study tools: measure the integrator and its parts on your own problems.

- `harness`: `work_precision` (final error, energy error, wall and compile time over a sweep
  of steps or tolerances) and `long_time_energy` (energy error over long horizons) for
  `Fixed`, `Adaptive` and `SciPy` solver entries.
- `stability`: the reference's stress sweep of `NetworkVI` (`stability_sweep`, `quick_grid`,
  `full_grid`, `convergence_rates`).
- `status`: `classify`, the one place that turns a finished solve into a status.
- `report`: markdown tables and PNG figures (matplotlib) from the rows.
- `suites`: the published configurations; `python -m diffrax_vi.bench --help` runs them.
- `seed_quality`: the OGA seed on its own (no integrator), over every configuration.
- `rounding_bias`: the oscillator's projected step solved exactly (long double), to measure
  the energy change rounding adds per step.
"""

from .harness import (
    Adaptive,
    Fixed,
    SciPy,
    iteration_summary,
    long_time_energy,
    read_rows,
    timed,
    work_precision,
    write_rows,
)
from .stability import (
    REFERENCE_RATES,
    StabilityCase,
    convergence_rates,
    full_grid,
    quick_grid,
    run_case,
    stability_sweep,
)
from .status import RESULT_STATUS, STATUSES, classify

__all__ = [
    "Adaptive",
    "Fixed",
    "SciPy",
    "iteration_summary",
    "long_time_energy",
    "timed",
    "read_rows",
    "work_precision",
    "write_rows",
    "REFERENCE_RATES",
    "StabilityCase",
    "convergence_rates",
    "full_grid",
    "quick_grid",
    "run_case",
    "stability_sweep",
    "RESULT_STATUS",
    "STATUSES",
    "classify",
]
