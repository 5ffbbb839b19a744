"""Benchmark and study tools: measure the integrator and its parts on your own problems.

- `entries`: how to run one solver (`Fixed`, `Adaptive`, `SciPy`, `Heyoka`).
- `harness`: `work_precision` (final error, energy error, wall and compile time over a sweep
  of steps or tolerances), `long_time_energy` (energy error over long horizons) and
  `growth_exponent` (the log-log growth of its running maximum) for those entries.
- `rows`: the rows as CSV (`write_rows`, `read_rows`).
- `stability`: the reference's stress sweep of `NetworkVI` (`stability_sweep`, `quick_grid`,
  `full_grid`); `stability_results`: what its rows say (`convergence_rates`, the restated
  target).
- `status`: `classify`, the one place that turns a finished solve into a status.
- `report`: markdown tables and PNG figures (matplotlib) from the rows.
- `suites`: the published configurations; `python -m diffrax_vi.bench --help` runs them.
- `peers`: heyoka's Taylor integrator as a peer (optional: the `peers` extra), generic over
  the problems' Hamiltonians (`hamilton`: their equations by sympy), with its ensemble
  runners.
"""

from .entries import Adaptive as Adaptive
from .entries import Fixed as Fixed
from .entries import Heyoka as Heyoka
from .entries import SciPy as SciPy
from .harness import growth_exponent as growth_exponent
from .harness import iteration_summary as iteration_summary
from .harness import long_time_energy as long_time_energy
from .harness import timed as timed
from .harness import work_precision as work_precision
from .rows import read_rows as read_rows
from .rows import write_rows as write_rows
from .stability import StabilityCase as StabilityCase
from .stability import full_grid as full_grid
from .stability import quick_grid as quick_grid
from .stability import run_case as run_case
from .stability import stability_sweep as stability_sweep
from .stability_results import REFERENCE_RATES as REFERENCE_RATES
from .stability_results import convergence_rates as convergence_rates
from .status import RESULT_STATUS as RESULT_STATUS
from .status import STATUSES as STATUSES
from .status import classify as classify
