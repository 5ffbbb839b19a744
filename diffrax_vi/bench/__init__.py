"""Benchmark and study tools: measure the integrator and its parts on your own problems.

- `harness`: `work_precision` (final error, energy error, wall and compile time over a sweep
  of steps or tolerances), `long_time_energy` (energy error over long horizons) and
  `growth_exponent` (the log-log growth of its running maximum) for `Fixed`, `Adaptive`,
  `SciPy` and `Heyoka` solver entries.
- `stability`: the reference's stress sweep of `NetworkVI` (`stability_sweep`, `quick_grid`,
  `full_grid`, `convergence_rates`).
- `status`: `classify`, the one place that turns a finished solve into a status.
- `report`: markdown tables and PNG figures (matplotlib) from the rows.
- `suites`: the published configurations; `python -m diffrax_vi.bench --help` runs them.
- `peers`: heyoka's Taylor integrator as a peer (optional: the `peers` extra), generic over
  the problems' Hamiltonians, with its ensemble runners.
"""

from .harness import Adaptive as Adaptive
from .harness import Fixed as Fixed
from .harness import Heyoka as Heyoka
from .harness import SciPy as SciPy
from .harness import growth_exponent as growth_exponent
from .harness import iteration_summary as iteration_summary
from .harness import long_time_energy as long_time_energy
from .harness import read_rows as read_rows
from .harness import timed as timed
from .harness import work_precision as work_precision
from .harness import write_rows as write_rows
from .stability import REFERENCE_RATES as REFERENCE_RATES
from .stability import StabilityCase as StabilityCase
from .stability import convergence_rates as convergence_rates
from .stability import full_grid as full_grid
from .stability import quick_grid as quick_grid
from .stability import run_case as run_case
from .stability import stability_sweep as stability_sweep
from .status import RESULT_STATUS as RESULT_STATUS
from .status import STATUSES as STATUSES
from .status import classify as classify
