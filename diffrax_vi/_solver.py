"""`NetworkVI`: a neural-network variational integrator as a diffrax solver."""

from __future__ import annotations

import functools
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from ._ansatz.base import AbstractBasis
from ._ansatz.shallow import ShallowNetBasis
from ._fallback import warn_all_parameter_fallback
from ._hidden_layers import UniformLayer
from ._interpolation import NetworkInterpolation
from ._precision import compensated_add
from ._quadrature import AbstractQuadrature, GaussLegendre
from ._results import JUMP_TOLERANCE, STEP_FAILURES, StepReport
from ._root_finder.damped_newton import LevenbergMarquardt
from ._root_finder.newton import RoundoffNewton
from ._seeding.policy import Seeder, SeedPolicy
from ._solver_options import check_options
from ._solver_state import NetworkVIState
from ._step.companion import companion_error, estimate_order
from ._step.degenerate import (
    CONSTRAINT_GROWTH,
    CONSTRAINT_TOLERANCE,
    end_on_constraint,
)
from ._step.energy_check import applies as energy_check_applies
from ._step.energy_check import relative_jump
from ._step.formulation import (
    AbstractFormulation,
    FreeEndpoints,
    SolveOptions,
    StepContext,
    node_momenta_and_forces,
    residual_scale,
    stage_values,
)
from ._step.holonomic import ConstrainedGalerkin, check_constrained_solver
from ._step.kinetic_check import kinetic_matrix_regular
from ._step.projection import VariableProjection
from ._terms import AbstractMechanicalTerm, unwrap_term
from ._validation import check_state, check_times, refuse_nonfinite_times

__all__ = ["NetworkVI", "NetworkVIState"]


class NetworkVI(diffrax.AbstractImplicitSolver):
    """Variational integrator whose trial curve on each step is a neural network (or any other
    ansatz): the step's unknowns solve the discrete Euler–Lagrange equations of the
    quadrature-approximated action. The state is `y = (q, p)` with the canonical momentum, the
    term a `LagrangianTerm` or `IODETerm`, and the working precision the dtype of `y0`. A step
    that fails ends the solve with one of the results of `diffrax_vi._results`.

    ```python
    import diffrax, jax.numpy as jnp, diffrax_vi as dvi

    term = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 0.5 * q @ q)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10))
    sol = diffrax.diffeqsolve(term, solver, 0.0, 1.0, 0.1, (jnp.ones(1), jnp.zeros(1)))
    ```

    **Arguments:**

    - `basis`: the ansatz (`ShallowNetBasis`, `DenseNetBasis`, `SymbolicAnsatz`,
      `LagrangeBasis`).
    - `quadrature`: the rule on `[0, 1]` for the action. Default `GaussLegendre(8)`.
    - `formulation`: `VariableProjection()` (the curve in the span of a fixed hidden layer,
      free endpoints: a square system with an isolated root), or the reference's
      all-parameter `FreeEndpoints()` / `InterpolatingEndpoints()`. Default `None`:
      `VariableProjection()` for a `ShallowNetBasis` without mirrored pairs whose activation
      `UniformLayer` suits, unless an option of the all-parameter step is given (a damped root
      finder, or a `seed` with `reuse_neurons`, `PreviousStep()` or an `initial_guess` other
      than the default); otherwise `FreeEndpoints()`, with an `AllParameterFallbackWarning`
      (once per activation) where a network's activation alone rules the projection out.
    - `seed`: where each step's solve starts, a `SeedPolicy` (its trajectory estimate, the fit
      of seed parameters to it, refits of the previous step's neurons). Default
      `SeedPolicy()`.
    - `root_finder`: the per-step root finder. Default `None`: for the projected step
      `RoundoffNewton(picard=True)` (not confirming on a network's span), which takes the
      Jacobian-free iteration wherever the Lagrangian's kinetic matrix is constant and
      Newton's method elsewhere; `LevenbergMarquardt()` for the all-parameter steps.
      `ChordIteration` also serves the projected step. A plain optimistix root finder
      gets none of the solver's options (residual scale, closed-form Jacobian, fallback
      seed) and stops on absolute tolerances.
    - `root_find_max_steps`: iteration cap of one step's solve. Default 100.
    - `adjoint`: how `optimistix.root_find` differentiates a converged step; the default
      solves the implicit-function system by least squares.
    - `iteration_log`: keep the iteration counts of the first `iteration_log` accepted steps in
      the solver state. Default 0.
    - `error_estimate`: for `diffrax.PIDController`. `None` (default): constant steps only.
      `True`: each step also solves a companion cGVI from the same start, of one degree more
      than a `LagrangeBasis` step's or, for a network, one more than the quadrature's
      number of nodes, and reports the difference of the end states as `y_error`: the step's own
      local error (measured at a median 0.97-1.01x of it on four problems), so the controller's
      steps follow the tolerance. A degree `j` chooses the companion; one of lower order
      than the step estimates the companion's error instead, and the steps are smaller
      than the tolerance needs. `error_order` is the estimate's order in `h`
      (`companion.estimate_order`). A failed step reports an infinite error, so the
      controller retries it smaller.
    - `compensated`: add the projected step's increments to the state by compensated
      summation, carrying the rounding in `NetworkVIState.compensation`. Default `True`.
    - `energy_check`: fail a converged step whose energy jumped far past the method's error
      (a wrong root of the step's equations, `RESULTS.vi_step_energy_jump`), where the
      energy is conserved: a `LagrangianTerm` that does not read the time and has no
      non-conservative force (`diffrax_vi._step.energy_check`). Default `True`.
    """

    basis: AbstractBasis
    quadrature: AbstractQuadrature = GaussLegendre(8)
    formulation: AbstractFormulation | None = None
    seed: SeedPolicy = SeedPolicy()
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = eqx.field(static=True, default=100)
    adjoint: optx.AbstractAdjoint = optx.ImplicitAdjoint(
        linear_solver=lx.AutoLinearSolver(well_posed=False)
    )
    error_estimate: int | bool | None = eqx.field(static=True, default=None)
    iteration_log: int = eqx.field(static=True, default=0)
    compensated: bool = eqx.field(static=True, default=True)
    energy_check: bool = eqx.field(static=True, default=True)

    term_structure: ClassVar = AbstractMechanicalTerm

    def __post_init__(self):
        # Checked first: the defaults below read the seed policy.
        if not isinstance(self.seed, SeedPolicy):
            raise TypeError(
                "seed must be a SeedPolicy (e.g. SeedPolicy(initial_guess=OGA1d())), got "
                f"{self.seed!r}"
            )
        if self.formulation is None:
            self.formulation = self._default_formulation()
        if self.root_finder is None:  # the formulation's own default
            if isinstance(self.formulation, VariableProjection):
                # On a network's feature span the confirming update moves the step onto the
                # root of the rounded residual, which is biased there (an energy drift; the
                # benchmarks page has the figures); on a polynomial span it removes the
                # first update's bias.
                confirm = not isinstance(self.basis, ShallowNetBasis)
                self.root_finder = RoundoffNewton(confirm=confirm, picard=True)
            else:
                self.root_finder = LevenbergMarquardt()

    def __check_init__(self):
        check_options(self)
        self.seed.check(self.basis, self.formulation)

    def _default_formulation(self) -> AbstractFormulation:
        """`VariableProjection()` where the ansatz and the other options allow it, else
        `FreeEndpoints()`: the projection's fixed layer needs a shallow network of an
        activation it suits; a damped root finder, `reuse_neurons`, `PreviousStep()` and a
        chosen `initial_guess` belong to the all-parameter step. A network left without the
        projection by its activation alone warns (`AllParameterFallbackWarning`)."""
        projectable = (
            isinstance(self.basis, ShallowNetBasis)
            and not self.basis.mirrored
            and UniformLayer.suits(self.basis.activation)
        )
        all_parameter_options = (
            self.seed.all_parameter_only
            or self.seed.fits_a_seed
            or not (self.root_finder is None or isinstance(self.root_finder, RoundoffNewton))
        )
        if projectable and not all_parameter_options:
            return VariableProjection()
        if isinstance(self.basis, ShallowNetBasis) and not self.basis.mirrored:
            if not all_parameter_options:  # the activation alone rules the projection out
                warn_all_parameter_fallback(self.basis)
        return FreeEndpoints()

    def solve_options_for(self, seeder: Seeder) -> SolveOptions:
        """What a formulation's solve of a step reads of this solver, with `seeder`."""
        return SolveOptions(self.root_finder, self.root_find_max_steps, self.adjoint, seeder)

    @property
    def solve_options(self) -> SolveOptions:
        """What `formulation`'s solve of a step reads of this solver."""
        return self.solve_options_for(self.seeder)

    @property
    def interpolation_cls(self):  # type: ignore[override]
        nodes = tuple(float(c) for c in self.quadrature.nodes_weights_np()[0])
        return _interpolation_factory(self.basis, self.formulation, nodes)

    def order(self, terms) -> int | None:
        return None

    def error_order(self, terms) -> int | None:
        # what diffrax's PIDController divides its exponents by: the estimate's order in h
        return estimate_order(self.error_estimate, self.basis, self.quadrature)

    # -- helpers --------------------------------------------------------------------------------
    def step_context(self, terms, t0, t1, y0, args) -> StepContext:
        """What one step from `t0` to `t1` works with: the term, the ansatz placed on the
        step, the start, the quadrature in the state's dtype."""
        term, direction = unwrap_term(terms)
        q0, p0 = check_state(y0)
        dtype = q0.dtype
        self.basis.check(dtype)
        with jax.ensure_compile_time_eval():  # constants of the compiled step, not traced
            nodes, weights = self.quadrature.nodes_weights(dtype)
        t = jnp.asarray(direction * t0, dtype)
        h = jnp.asarray(direction * (t1 - t0), dtype)
        basis = self.basis.at_step(t, h)
        return StepContext(term, basis, t, h, q0, p0, args, nodes, weights)

    def formulation_for(self, term) -> AbstractFormulation:
        """The formulation of this term's steps (decided when the step is traced): the
        constrained Galerkin step where it has holonomic constraints, else `formulation`."""
        return ConstrainedGalerkin() if term.has_constraints else self.formulation

    def seeder_for(self, formulation: AbstractFormulation) -> Seeder:
        """The seed policy bound to this solver's ansatz and root finder and `formulation`."""
        return self.seed.bind(self.basis, formulation, self.root_finder)

    @property
    def seeder(self) -> Seeder:
        """The seed policy bound to this solver's ansatz, formulation and root finder."""
        return self.seeder_for(self.formulation)

    # -- diffrax.AbstractSolver interface -----------------------------------------------------
    def init(self, terms, t0, t1, y0, args) -> NetworkVIState:
        # Concrete times (manual stepping) are refused at trace time. Inside `diffeqsolve` they
        # are traced by now and are checked when the program runs: a NaN time would make
        # diffrax take no step and report success. The checked `t0` reaches `report.t`, which
        # every step reads, so the check stays in the program.
        check_times(t0=t0, t1=t1)
        t0 = refuse_nonfinite_times(t0, t1)
        ctx = self.step_context(terms, t0, t1, y0, args)
        from ._step.kinetic_check import refuse_degenerate_start  # a start no step can solve
        ctx = refuse_degenerate_start(ctx)  # its `t` reaches `report.t`, as the times' check
        if ctx.term.has_constraints:
            check_constrained_solver(self.basis, self.error_estimate)
        seed = self.seeder_for(self.formulation_for(ctx.term)).first_record(ctx)
        zero = jnp.array(0, jnp.int32)
        return NetworkVIState(
            seed=seed,
            iterations=zero,
            last_iterations=zero,
            max_iterations=zero,
            steps=zero,
            histogram=jnp.zeros(self.root_find_max_steps + 1, jnp.int32),
            warm_starts=zero,
            refits=zero,
            restarts=zero,
            iteration_log=jnp.full(self.iteration_log, -1, jnp.int32),
            report=StepReport(
                t=ctx.t,
                h=ctx.h,
                residual=jnp.zeros((), ctx.q0.dtype),
                tolerance=jnp.full((), jnp.nan, ctx.q0.dtype),
                iterations=zero,
                result=diffrax.RESULTS.successful,
                constraint=jnp.zeros((), ctx.q0.dtype),
                energy_jump=jnp.zeros((), ctx.q0.dtype),
            ),
            first_constraint=jnp.full((), jnp.nan, ctx.q0.dtype),
            compensation=(jnp.zeros_like(ctx.q0), jnp.zeros_like(ctx.p0)),
            holonomic_drift=jnp.zeros(2, ctx.q0.dtype),
        )

    def step(self, terms, t0, t1, y0, args, solver_state: NetworkVIState, made_jump):
        # Python-number times become arrays (a static argument of the jitted step would be
        # traced again for every value), in the state's dtype, as they would combine with it.
        leaves = jax.tree_util.tree_leaves(y0)
        dtype = jnp.result_type(*leaves) if leaves else None
        t0, t1 = (
            jnp.asarray(t, dtype) if isinstance(t, int | float) else t for t in (t0, t1)
        )
        return _traced_once(type(self)._step)(
            self, terms, t0, t1, y0, args, solver_state, made_jump
        )

    def _step(self, terms, t0, t1, y0, args, solver_state: NetworkVIState, made_jump):
        """Seed -> solve -> accept."""
        ctx = self.step_context(terms, t0, t1, y0, args)
        state = solver_state
        formulation = self.formulation_for(ctx.term)
        seeding = self.seeder_for(formulation)
        record = seeding.after_jump(state.seed, made_jump)
        seed = seeding.seed(ctx, record, made_jump, state.report.residual, state.last_iterations)
        solved = formulation.solve_step(ctx, seed, self.solve_options_for(seeding))
        if solved.increments is not None:  # added here, compensated
            q1, p1, compensation = self._add_increments(ctx, state, *solved.increments)
        else:
            (q1, p1), compensation = solved.end, state.compensation
        q1, p1 = q1.astype(ctx.q0.dtype), p1.astype(ctx.p0.dtype)
        violation = None  # known when traced: a regular kinetic matrix has no primary constraint
        if formulation.has_primary_constraint and not kinetic_matrix_regular(ctx):
            # a first-order Lagrangian's end state: moved onto its primary constraint where the
            # step solved in increments (a moved coordinate carries no compensation)
            moved, violation = end_on_constraint(ctx, q1, p1,
                                                 correct=solved.increments is not None)
            compensation = (jnp.where(moved == q1, compensation[0], 0), compensation[1])
            q1 = moved
        return self._finish_step(ctx, state, seeding, record, seed, solved, q1, p1,
                                 compensation, violation)

    def _add_increments(self, ctx, state, dq, dp):
        """`(q1, p1, compensation)`: the step's start plus its increments (compensated where
        `NetworkVI.compensated`)."""
        if self.compensated:
            (q1, eq), (p1, ep) = (
                compensated_add(x, d, e)
                for x, d, e in zip((ctx.q0, ctx.p0), (dq, dp), state.compensation, strict=True)
            )
            return q1, p1, (eq, ep)
        q1, p1 = ctx.q0 + dq.astype(ctx.q0.dtype), ctx.p0 + dp.astype(ctx.p0.dtype)
        return q1, p1, state.compensation

    def _step_result(self, ctx, state, formulation, q1, p1, result, violation):
        """`(finite, result, constraint, first, jump)`: whether the end state is finite, the
        step's result with the failures that only the end state shows (not finite, an invalid
        step, drift off the primary constraint, an energy jump), the constraint distance
        relative to the residual scale, the run's first such distance, and the step's
        relative energy jump (0 where it is not checked)."""
        finite = jnp.all(jnp.isfinite(q1)) & jnp.all(jnp.isfinite(p1))
        result = diffrax.RESULTS.where(
            finite | (result != diffrax.RESULTS.successful),
            result,
            STEP_FAILURES["vi_step_nonfinite"],
        )
        # `state.report.t` (the previous step's time, or the checked `t0`) is read here so that
        # `init`'s run-time check of the times is part of every solve's program.
        invalid = (ctx.h == 0) | ~jnp.isfinite(ctx.h) | ~jnp.isfinite(state.report.t)
        result = diffrax.RESULTS.where(invalid, STEP_FAILURES["vi_step_size_invalid"], result)
        if violation is None:  # no primary constraint, known when traced: nothing to track
            constraint = jnp.zeros((), ctx.q0.dtype)
            first = jnp.where(jnp.isnan(state.first_constraint), 0, state.first_constraint)
            result, jump = self._energy_jump(ctx, q1, p1, result)
            return finite, result, constraint, first, jump
        scale = residual_scale(ctx)
        constraint = (violation / scale).astype(ctx.q0.dtype)
        first = jnp.where(jnp.isnan(state.first_constraint), constraint, state.first_constraint)
        # Drift is growth: above eps^CONSTRAINT_TOLERANCE and CONSTRAINT_GROWTH times the
        # distance of the run's first step (a bounded distance is the step's truncation error).
        # Only where the step's roots are not isolated (the all-parameter step of a nonlinear
        # ansatz) can the end state walk off the constraint from step to step.
        drift = (constraint > float(jnp.finfo(ctx.q0.dtype).eps) ** CONSTRAINT_TOLERANCE) & (
            constraint > CONSTRAINT_GROWTH * first
        )
        drift = drift & formulation.roots_may_drift(self.basis)
        result = diffrax.RESULTS.where(
            drift & (result == diffrax.RESULTS.successful),
            STEP_FAILURES["vi_constraint_drift"],
            result,
        )
        result, jump = self._energy_jump(ctx, q1, p1, result)
        return finite, result, constraint, first, jump

    def _energy_jump(self, ctx, q1, p1, result):
        """`(result, jump)`: a converged step whose energy jumped far past the method's error
        is a wrong root (`vi_step_energy_jump`); `jump` is 0 where it is not checked."""
        jump = jnp.zeros((), ctx.q0.dtype)
        if self.energy_check and energy_check_applies(ctx.term, ctx.t, ctx.q0, ctx.args):
            jump = relative_jump(ctx.term, ctx.t, ctx.q0, ctx.p0, q1, p1, ctx.args)
            result = diffrax.RESULTS.where(
                (jump > JUMP_TOLERANCE) & (result == diffrax.RESULTS.successful),
                STEP_FAILURES["vi_step_energy_jump"],
                result,
            )
        return result, jump

    def _finish_step(self, ctx, state, seeding, record, seed, solved, q1, p1, compensation,
                     violation):
        """Failure results, dense output, the new solver state (the seed policy's record
        accepts the step) of the step `solved` that ends at `(q1, p1)`. `violation` is the
        end state's distance from the primary constraint (`end_on_constraint`)."""
        formulation, theta, n = seeding.formulation, solved.theta, solved.iterations
        finite, result, constraint, first, jump = self._step_result(
            ctx, state, formulation, q1, p1, solved.result, violation)
        result = _computed_once(result)
        # A failed step's end state is never passed off as data: the steps before it stay,
        # this one is NaN (with `throw=False`), and `report` says where and why it failed.
        failed = result != diffrax.RESULTS.successful
        # A factor of NaN (failed) or 1: derivatives through a failed step are NaN too, and
        # those of a successful one are untouched (a `where` over `NaN * q1` would leak NaN
        # into them). The carried compensation of a failed step is NaN as well.
        poison = _nan_if(failed, ctx.q0.dtype)
        q1 = q1 * poison
        p1 = p1 * poison

        def curve(tau):
            return formulation.position(ctx.basis, theta, ctx.q0, q1, tau)

        forces = solved.forces
        if forces is None:
            q_nodes, dq_nodes = stage_values(curve, ctx.nodes)
            _, forces = node_momenta_and_forces(ctx, q_nodes, dq_nodes)
        f_nodes = forces
        dense_info = dict(
            theta=theta,
            q0=ctx.q0,
            q1=q1,
            p0=ctx.p0,
            p1=p1,
            f_nodes=f_nodes.astype(ctx.p0.dtype),
            t_step=ctx.t,
            h_step=ctx.h,
        )
        for key in ("theta", "f_nodes"):  # dense output of a failed step is NaN too
            dense_info[key] = jax.tree_util.tree_map(
                lambda a: jnp.where(failed, jnp.asarray(jnp.nan, a.dtype), a), dense_info[key]
            )
        new_state = NetworkVIState(
            seed=seeding.accept(ctx, record, theta, curve, q1, solved.node_values),
            iterations=state.iterations + n,
            last_iterations=n,
            max_iterations=jnp.maximum(state.max_iterations, n),
            steps=state.steps + 1,
            histogram=state.histogram.at[jnp.minimum(n, self.root_find_max_steps)].add(1),
            warm_starts=state.warm_starts + seed.warm.astype(jnp.int32),
            refits=state.refits + seed.refitted.astype(jnp.int32),
            restarts=state.restarts + solved.restarted.astype(jnp.int32),
            iteration_log=(
                state.iteration_log.at[state.steps].set(n, mode="drop")
                if self.iteration_log
                else state.iteration_log
            ),
            report=StepReport(
                t=ctx.t,
                h=ctx.h,
                residual=solved.residual,
                tolerance=solved.tolerance,
                iterations=n,
                result=result,
                constraint=constraint,
                energy_jump=jump,
            ),
            first_constraint=first,
            compensation=jax.tree_util.tree_map(
                lambda e: e * poison.astype(e.dtype), compensation
            ),
            holonomic_drift=(state.holonomic_drift if solved.drift is None
                             else jnp.maximum(state.holonomic_drift, solved.drift)),
        )
        y_error = None
        if self.error_estimate is not None:
            ok = (result == diffrax.RESULTS.successful) & finite
            y_error = companion_error(self.error_estimate, self.solve_options_for(seeding), ctx,
                                      curve, q1, p1, ok)
        return (q1, p1), y_error, dense_info, new_state, result

    def func(self, terms, t0, y0, args):
        # Hamilton's equations without constraints: diffrax reads their size for `dt0`.
        term, direction = unwrap_term(terms)
        return term.hamilton_vf(direction * t0, check_state(y0), args)


def _computed_once(result):
    """`result` (a `RESULTS` item: a small non-negative code) read back through a square
    root, `round(√c · √c)`, exact for codes this small. XLA copies cheap element-wise
    producers into every consumer fusion, so each user of the code (the state's failure
    factor, its report, diffrax's own bookkeeping) would recompute the step's whole failure
    test; a square root is not copied, so the test runs once and the users only square it."""
    code = jax.tree_util.tree_leaves(result)[0]
    root = jnp.sqrt(code.astype(jnp.float32))
    value = jnp.round(root * root).astype(code.dtype)
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(result), [value])


def _nan_if(failed: jax.Array, dtype) -> jax.Array:
    """NaN where `failed`, else 1, as `√(1 − 2·failed)`. XLA copies cheap element-wise
    producers into every consumer fusion, so a `where` on `failed` per state leaf would
    recompute the step's whole failure test (its result code) once per leaf; a square root
    is not copied, so the test is computed once and each leaf only multiplies by it."""
    return jnp.sqrt(1 - 2 * failed.astype(dtype))


@functools.cache
def _traced_once(step):
    """`step` jitted: diffrax traces a solver's step up to three times while building its
    loop (twice to find the loop's types); a jitted step is traced once per signature and
    the other traces reuse it."""
    return eqx.filter_jit(step)


@functools.lru_cache(maxsize=64)
def _interpolation_factory(
    basis: AbstractBasis, formulation: AbstractFormulation, nodes: tuple[float, ...]
):
    return functools.partial(
        NetworkInterpolation, basis=basis, formulation=formulation, nodes=nodes
    )
