"""How the benchmark harness runs one solver: its entries `Fixed`, `Adaptive`, `SciPy` and
`Heyoka`, each with its sweep parameter (`steps` over the span, or `rtol`)."""

from __future__ import annotations

import dataclasses

import diffrax

__all__ = ["Adaptive", "Entry", "Fixed", "Heyoka", "NotSeparable", "SciPy", "retry_step_budget"]


@dataclasses.dataclass(frozen=True)
class Fixed:
    """A diffrax solver on constant steps (sweep parameter: steps over the span).

    **Arguments:**

    - `name`: label in the tables and plots.
    - `solver`: the diffrax solver, e.g. `NetworkVI(...)`, `CGVI(7)`, `SemiImplicitEuler()`.
    - `separable`: integrate the pair `term.separable_terms(y0)` (for `SemiImplicitEuler`);
      a problem that is not separable is skipped with status `error:NotSeparable`.
    - `family`: `"ours"` for the NetworkVI variants, `"peer"` for the others (the reports
      compare the best of each).
    - `retry`: step with `RetryFailedSteps()` instead of `ConstantStepSize()`, so that a
      failed step is taken again in pieces instead of ending the run (`steps` then counts
      the pieces, `rejected` the failed trials).
    """

    name: str
    solver: diffrax.AbstractSolver
    separable: bool = False
    family: str = "peer"
    retry: bool = False
    kind = "fixed"
    parameter = "steps"

    def step_budget(self, steps: int) -> int:
        """`max_steps` for a run of `steps` grid steps: room for retries where `retry`."""
        return retry_step_budget(steps) if self.retry else steps


def retry_step_budget(steps: int) -> int:
    """`max_steps` for `steps` grid steps under `RetryFailedSteps`: every failed trial and
    every piece of a retried interval is a step of its own."""
    return 2 * steps + 100


@dataclasses.dataclass(frozen=True)
class Adaptive:
    """A diffrax solver with `PIDController(rtol, atol=atol_ratio * rtol)` (sweep: `rtol`)."""

    name: str
    solver: diffrax.AbstractSolver
    atol_ratio: float = 1e-2
    family: str = "peer"
    kind = "adaptive"
    parameter = "rtol"


@dataclasses.dataclass(frozen=True)
class SciPy:
    """`scipy.integrate.solve_ivp(method=...)` with `atol = atol_ratio * rtol` (sweep: `rtol`).

    The right-hand side is the problem's NumPy vector field when it carries one (the problems
    with a stored or DOP853 reference), else the term's Hamilton equations jitted by JAX and
    called once per evaluation.
    """

    name: str = "scipy DOP853"
    method: str = "DOP853"
    atol_ratio: float = 1e-2
    family: str = "peer"
    kind = "scipy"
    parameter = "rtol"


@dataclasses.dataclass(frozen=True)
class Heyoka:
    """heyoka's adaptive Taylor integrator (sweep: its `tol`, passed as the `rtols`).

    Optional: it needs heyoka (`pip install "diffrax_vi[peers]"`); a run without it is a row
    with status `error:ImportError`. Hamilton's equations come from the problem's Hamiltonian
    (`bench.peers.heyoka_system`); one integrator is built per (problem, tol), its build
    (LLVM compilation, without heyoka's caches) in `compile_s`. The energy error is read at
    the step ends of one more, untimed, run.
    """

    name: str = "heyoka"
    compact_mode: bool = False
    high_accuracy: bool = False
    family: str = "peer"
    kind = "heyoka"
    parameter = "rtol"


Entry = Fixed | Adaptive | SciPy | Heyoka


class NotSeparable(ValueError):
    """The problem's Lagrangian is not `T(v) − V(q)`, so a split solver cannot run it."""
