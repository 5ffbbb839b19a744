"""`NetworkVIState`: what `NetworkVI` carries from one step to the next."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, PyTree

from ._results import StepReport
from ._seeding.policy import SeedRecord
from ._seeding.trajectories import StepHistory

__all__ = ["NetworkVIState"]


class NetworkVIState(eqx.Module):
    """What `NetworkVI` carries from step to step (read it with `SaveAt(solver_state=True)`).

    - `seed`: what the seed policy carries (`diffrax_vi._seeding.policy.SeedRecord`), also
      read as the state's own attributes:
      - `theta`: the last converged parameters; before the first step they are zeros and
        `fresh` is true (the first step is always seeded by a trajectory fit).
      - `h_prev`: the length of the step `theta` belongs to.
      - `history`: the previous step's ends (`StepHistory`), for `HermiteExtrapolation`.
    - `iterations`: total nonlinear iterations over all accepted steps.
    - `last_iterations`, `max_iterations`: of the last step, and the most of any step.
    - `steps`: number of steps taken.
    - `histogram`: `histogram[k]` = number of steps that needed `k` iterations (the last
      bin also counts steps that ran out of iterations), e.g. for the median per step.
    - `warm_starts`: number of steps seeded by `PreviousStep`'s warm start (the others were
      seeded by a trajectory fit).
    - `refits`: number of steps seeded by the previous step's neurons with refitted output
      weights instead of a fresh OGA fit (`SeedPolicy.reuse_neurons`).
    - `restarts`: number of steps whose solve failed from a seed carried over from the
      previous step (warm start or refit) and restarted from a fresh trajectory fit (with
      `LevenbergMarquardt` or `RegularisedNewton`; the iteration cap covers both tries).
    - `iteration_log`: the iterations of each accepted step, in order, for the first
      `NetworkVI.iteration_log` steps (empty by default).
    - `report`: how the most recent step's nonlinear solve ended (`StepReport`: start time,
      length, residual, tolerance, iterations, result). After a failed solve with constant
      steps this is the failed step; `diffrax_vi.describe_failure(sol)` prints it.
    - `first_constraint`: `report.constraint` of the run's first step (NaN before it), the
      scale against which the constraint monitor measures growth.
    - `compensation`: `(e_q, e_p)`, the rounding left over from adding the last step's
      increments to `q` and `p` (compensated summation, `NetworkVI.compensated`): the
      state is `y + compensation` to about twice the working precision. Zeros when off.
    - `node_values` (read off `seed`): `(F, G)`, each `(R, D)`: the forces and the
      momentum's offsets at the nodes of the last accepted step, from which the
      Jacobian-free iteration starts the next; for a term with holonomic constraints, the
      last step's values and impulses at its Lobatto points
      (`diffrax_vi._step.holonomic.PreviousStep`), from which the next constrained step
      starts; `None` where neither is used.
    - `holonomic_drift`: `(2,)`, for a term with holonomic constraints the largest
      `|g(t, q)|` and `|G(q) v + ∂g/∂t|` at the ends of the steps so far (position and
      velocity level); zeros without constraints.
    """

    seed: SeedRecord
    iterations: Array
    last_iterations: Array
    max_iterations: Array
    steps: Array
    histogram: Array
    warm_starts: Array
    refits: Array
    restarts: Array
    iteration_log: Array
    report: StepReport
    first_constraint: Array
    compensation: tuple[Array, Array]
    holonomic_drift: Array

    @property
    def theta(self) -> PyTree:
        return self.seed.theta

    @property
    def fresh(self) -> Array:
        return self.seed.fresh

    @property
    def h_prev(self) -> Array:
        return self.seed.h_prev

    @property
    def node_values(self) -> tuple[Array, Array] | None:
        return self.seed.node_values

    @property
    def history(self) -> StepHistory:
        return self.seed.history
