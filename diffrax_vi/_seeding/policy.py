"""`NetworkVI`'s seed policy: where each step's nonlinear solve starts, and what it carries
from one step to the next to choose that start.

A user picks a `SeedPolicy` (`NetworkVI(seed=...)`); the solver binds it to its ansatz,
formulation and root finder as a `Seeder`. A step reads: `Seeder.seed` (the start, from the
`SeedRecord` carried in the solver state) -> the solve -> `Seeder.accept` (the record after
the converged step). Neither holds state of its own.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from .._ansatz.base import AbstractBasis
from .._ansatz.shallow import ShallowNetBasis
from .._hidden_layers import FirstSeedLayer, UniformLayer
from .._lazy import unless_all_skip
from .._parameter_seed import AbstractParameterSeed, fit_problem, with_constant_grid
from .._root_finder.damped_newton import AbstractDampedNewton
from .._root_finder.step_hints import StepHints, traits_of
from .._step.formulation import (
    AbstractFormulation,
    CurveSamples,
    FreeEndpoints,
    StepContext,
    residual_scale,
    stage_values,
)
from .._step.jacobian_free import extrapolation, picard_engine, start_at_rest
from .._step.projection import VariableProjection
from ..oga import AbstractOGA, OGA1d
from .fit import refit_output_weights
from .trajectories import (
    AbstractInitialTrajectory,
    HermiteExtrapolation,
    IntegratorExtrapolation,
    PreviousStep,
    StepHistory,
    labels_curve,
)

__all__ = ["Seed", "SeedPolicy", "SeedRecord", "Seeder"]


class SeedPolicy(eqx.Module):
    """Where each step's nonlinear solve starts: the solver's `seed` option.

    A seed is a fit (`initial_guess`) of a trajectory estimate (`initial_trajectory`) over the
    step. The all-parameter step may instead start from the previous step's neurons with their
    output weights refitted (`reuse_neurons`), or from the previous curve continued
    (`PreviousStep()`). The default projected step (`VariableProjection()`) carries its hidden
    layer from step to step and restarts from `initial_trajectory` where its start from the
    previous curve does not converge; it fits no seed unless its `hidden` rule asks for one.

    **Arguments:**

    - `initial_trajectory`: the trajectory estimate a seed is fitted to:
      `IntegratorExtrapolation()` (default), `HermiteExtrapolation()`, `NoExtrapolation()`, or
      `PreviousStep()` (the previous curve continued, for the all-parameter step).
    - `initial_guess`: how seed parameters are fitted to that trajectory: an OGA configuration
      (default `OGA1d()`, which also holds the dictionary's `bias_interval` and
      `dict_amount`), `LSGD()`, `TrainingMethod()`, `LeastSquaresFit()` (linear ansätze),
      `InitialWeights(...)`, `TrajectoryFit()`, or any `AbstractParameterSeed`.
    - `reuse_neurons`: seed an all-parameter step with the previous step's neurons and output
      weights refitted to the new trajectory, where that fit is within `refit_tolerance`
      (default `√eps`); otherwise, and on the first step, run the OGA. Default `False`.
    - `refit_residual`, `refit_iterations`: refit only from a previous step whose solve ended
      at most at this relative residual, or within this many iterations (default `None`: no
      limit); guards for long runs (choosing page).
    - `restart_failed`: where a solve from a seed carried over from the previous step fails,
      restart it once from a fresh fit. Default `True`.
    """

    initial_trajectory: AbstractInitialTrajectory = IntegratorExtrapolation()
    initial_guess: AbstractParameterSeed = OGA1d()
    reuse_neurons: bool = eqx.field(static=True, default=False)
    refit_tolerance: float | None = eqx.field(static=True, default=None)
    refit_residual: float | None = eqx.field(static=True, default=None)
    refit_iterations: int | None = eqx.field(static=True, default=None)
    restart_failed: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        _check_policy(self)

    @property
    def all_parameter_only(self) -> bool:
        """Whether this policy belongs to the all-parameter step only (the previous curve
        continued, or refitted neurons)."""
        return self.reuse_neurons or isinstance(self.initial_trajectory, PreviousStep)

    @property
    def fits_a_seed(self) -> bool:
        """Whether `initial_guess` is other than the default `OGA1d()`: a choice that only a
        step that fits seeds can honour."""
        return self.initial_guess != OGA1d()

    def check(self, basis: AbstractBasis, formulation: AbstractFormulation) -> None:
        """Refuse a policy that does not fit the ansatz or the formulation, naming the option."""
        _check_policy_against(self, basis, formulation)

    def bind(
        self, basis: AbstractBasis, formulation: AbstractFormulation, root_finder
    ) -> Seeder:
        """The policy as a solver with this ansatz, formulation and root finder runs it.
        Refits need an OGA-seeded `ShallowNetBasis`; the fresh fit is left to the root finder
        where it is damped (it takes a fallback) and the seed may be carried over from the
        previous step."""
        refits = self.reuse_neurons and _can_refit(basis, self.initial_guess)
        lazy = isinstance(root_finder, AbstractDampedNewton) and (
            isinstance(self.initial_trajectory, PreviousStep) or refits
        )
        engine = traits_of(root_finder).allows_picard()
        return Seeder(self, formulation, refits, lazy, engine)


class SeedRecord(eqx.Module):
    """What the seed policy carries from step to step.

    - `theta`: the last converged parameters; before the first step they are zeros and
      `fresh` is true (the first step is always seeded by a trajectory fit).
    - `h_prev`: the length of the step `theta` belongs to.
    - `history`: the previous step's ends (`StepHistory`), for `HermiteExtrapolation`.
    - `node_values`: where the step takes the Jacobian-free iteration, `(F, G)`, each
      `(R, D)`: the forces and the momentum's offsets at the nodes of the last step's curve
      (before the first step, of the curve at rest), from which the next step starts; for
      a formulation that continues itself, what its last solve left; else `None`.
    """

    theta: PyTree
    fresh: Array
    h_prev: Array
    history: StepHistory
    node_values: Any = None


class Seed(NamedTuple):
    """A step's start, as the policy chose it.

    - `start`: the all-parameter unknowns; for `VariableProjection`, `(hidden, start)`: the
      parameters whose hidden layer spans the step, and the function of the span that gives
      the solve's start (a curve projected on the span, and the start of `p_{n+1}`).
    - `warm`, `refitted`: whether the start carries the previous step's curve continued, or
      its neurons with refitted output weights (the solver counts both).
    - `cold_inputs`, `fit_inputs`: what the root finder's fallback (the fresh fit) is computed
      from: the record's `(theta, fresh, history)`, and the fit's inputs where the step
      computed them already (else `None`).
    - `restart_history`: for the projected steps that start from the previous curve
      continued, the history their restart from the trajectory seed reads (else `None`).
    - `engine`: where the step takes the Jacobian-free iteration, `(Engine, (F, G))`: what
      the iteration is built from (`_step.jacobian_free.picard_engine`) and the last step's
      node values continued over this step, from which it starts (else `None`).
    """

    start: Any
    warm: Array
    refitted: Array
    cold_inputs: tuple | None = None
    fit_inputs: tuple | None = None
    restart_history: StepHistory | None = None
    engine: tuple | None = None


class Seeder(eqx.Module):
    """A `SeedPolicy` bound to a solver (`SeedPolicy.bind`): the seeds of its steps.

    The all-parameter step starts from a fit (`initial_guess`) of the trajectory seed
    (`initial_trajectory`), from the previous step's neurons with refitted output weights
    (`refits`), or from the previous curve continued (`PreviousStep`). With a damped root
    finder and a seed that may be carried over (`lazy`), the fresh fit is the root finder's
    fallback instead, computed only where the carried seed is unusable or its solve fails.
    `VariableProjection` seeds its hidden layer by its `hidden` rule, and where the root
    finder allows the Jacobian-free iteration (`engine`) and the step offers it, starts from
    the last step's node values continued.
    """

    policy: SeedPolicy
    formulation: AbstractFormulation
    refits: bool = eqx.field(static=True)
    lazy: bool = eqx.field(static=True)
    engine_allowed: bool = eqx.field(static=True, default=False)

    @property
    def initial_trajectory(self) -> AbstractInitialTrajectory:
        return self.policy.initial_trajectory

    # -- the record --------------------------------------------------------------------------
    def first_record(self, ctx: StepContext) -> SeedRecord:
        """The record before the first step, which seeds itself (`fresh`): computing its seed
        here would put a second copy of the seed fit into the compiled program."""
        theta = ctx.basis.zeros(ctx.q0.shape[0], ctx.q0.dtype)
        if self.formulation.continues_itself:
            values = self.formulation.first_start(ctx)
        else:
            values = start_at_rest(ctx) if self.engine(ctx) is not None else None
        return SeedRecord(theta, jnp.array(True), ctx.h, StepHistory.empty(ctx.q0, ctx.t),
                          values)

    def engine(self, ctx: StepContext):
        """The Jacobian-free iteration's `Engine` where this step takes it, else `None`
        (decided when the step is traced: `_step.jacobian_free.picard_engine`)."""
        return picard_engine(self.engine_allowed, self.formulation, ctx)

    @staticmethod
    def after_jump(record: SeedRecord, made_jump) -> SeedRecord:
        """The record across a jump of the state: the previous step's ends no longer apply."""
        if made_jump is False:
            return record
        return eqx.tree_at(lambda r: r.history.valid, record, record.history.valid & ~made_jump)

    def accept(self, ctx: StepContext, record: SeedRecord, theta, curve, q1,
               node_values=None) -> SeedRecord:
        """The record after the step to `q1` along `curve` with parameters `theta` (and the
        node values of its curve, where the step took the Jacobian-free iteration)."""
        if self.formulation.continues_itself:  # nothing else of the record is read
            return eqx.tree_at(lambda r: r.node_values, record, node_values)
        # Only Hermite extrapolation reads the previous step's ends; skip the work otherwise.
        history = _history(ctx, curve, q1) if self.uses_history else record.history
        if record.node_values is None:
            node_values = None
        return SeedRecord(theta, jnp.array(False), ctx.h, history, node_values)

    @property
    def uses_history(self) -> bool:
        trajectory = self.initial_trajectory
        if isinstance(trajectory, PreviousStep):
            trajectory = trajectory.first
        return isinstance(trajectory, HermiteExtrapolation)

    # -- the start of a step -----------------------------------------------------------------
    def seed(
        self, ctx: StepContext, record: SeedRecord, made_jump, last_residual, last_iterations
    ) -> Seed:
        """The start of the step from `record`; `last_residual` and `last_iterations` are how
        the previous step's solve ended (for the refit guards)."""
        if self.formulation.continues_itself:  # its last solve, unless the state jumped
            carried = record.node_values
            if made_jump is not False:
                carried = carried._replace(valid=carried.valid & ~made_jump)
            return Seed(carried, jnp.array(False), jnp.array(False))
        engine = self.engine(ctx) if record.node_values is not None else None
        if engine is not None:
            return self._engine_seed(ctx, record, made_jump, engine)
        cold_inputs = (record.theta, record.fresh, record.history)
        refit_ok = (
            self._refit_allowed(ctx, last_residual, last_iterations)
            if self.refits
            else jnp.array(False)
        )
        projected = isinstance(self.formulation, VariableProjection)
        rule = self.formulation.hidden if projected else None
        if isinstance(rule, UniformLayer | FirstSeedLayer):
            return self._carried_layer_seed(ctx, record, rule, cold_inputs)
        warm_used = jnp.array(False)
        fit_inputs = None  # the seed fit's inputs, where computed outside a `cond`
        if self.lazy and not self.refits:
            # Only a warm start can be carried over; the fresh fit is the root finder's.
            warm = self._warm_seed(ctx, record)
            warm_used = self._warm_acceptable(warm, ctx, record, made_jump)
            seed, refitted = warm, jnp.array(False)
        elif isinstance(self.initial_trajectory, PreviousStep):
            warm = self._warm_seed(ctx, record)
            warm_used = self._warm_acceptable(warm, ctx, record, made_jump)
            seed, refitted = jax.lax.cond(
                warm_used,
                lambda: (warm, jnp.array(False)),
                lambda: self.cold_seed(
                    ctx, *cold_inputs, lazy=self.lazy, refit_ok=refit_ok
                )[:2],
            )
        else:
            seed, refitted, fit_inputs = self.cold_seed(
                ctx, *cold_inputs, lazy=self.lazy, refit_ok=refit_ok
            )
        if projected:  # `SeedLayer`: the span of this step's own seed
            start = self._projected_start(ctx, functools.partial(ctx.basis.evaluate, seed[0]),
                                          seed[1])
            return Seed((seed[0], start), warm_used, refitted)
        return Seed(seed, warm_used, refitted, cold_inputs, fit_inputs)

    def _engine_seed(self, ctx: StepContext, record: SeedRecord, made_jump, engine) -> Seed:
        """The Jacobian-free iteration's start: the node values of the last step continued
        over this one (`extrapolation`), or those of the curve at rest after a jump of the
        state. A start only: nothing of it is differentiated."""
        nodes = np.asarray(self.formulation_nodes(ctx))
        ratio = ctx.h / record.h_prev
        forces, offsets = jax.lax.stop_gradient(record.node_values)
        forces = extrapolation(nodes, ratio, forces)
        if engine.structure.offset_moves:
            offsets = extrapolation(nodes, ratio, offsets)
        fresh = record.fresh
        if made_jump is not False:
            rest = start_at_rest(ctx)
            forces = jnp.where(made_jump, rest[0], forces)
            offsets = jnp.where(made_jump, rest[1], offsets)
            fresh = fresh | made_jump
        return Seed((None, None), ~fresh, jnp.array(False), engine=(engine, (forces, offsets)))

    @staticmethod
    def formulation_nodes(ctx: StepContext):
        """The quadrature's nodes as constants (they are when the step is traced)."""
        with jax.ensure_compile_time_eval():
            return np.asarray(ctx.nodes, np.float64)

    def _carried_layer_seed(self, ctx: StepContext, record: SeedRecord, rule, cold_inputs):
        """A projected step whose hidden layer is carried from step to step (`UniformLayer`,
        `FirstSeedLayer`): after the first step, every step starts from the previous curve
        continued; the first starts from a seed fit (`FirstSeedLayer`) or from the constant
        curve q_n."""
        warm = self._warm_seed(ctx, record)
        if isinstance(rule, UniformLayer) or not isinstance(ctx.basis, ShallowNetBasis):
            dim = ctx.q0.shape[0]
            # Constants of the compiled step, not traced: the span built on them is then
            # computed once, when the step is traced (`VariableProjection.span`).
            if isinstance(ctx.basis, ShallowNetBasis):
                with jax.ensure_compile_time_eval():
                    hidden = rule.parameters(ctx.basis, dim, ctx.q0.dtype)
            else:  # a linear ansatz: its span has no hidden layer to choose
                # zeros in NumPy, of the placeholder's structure (no eager programs)
                shapes = jax.eval_shape(lambda: ctx.basis.zeros(dim, ctx.q0.dtype))
                hidden = jax.tree_util.tree_map(lambda s: np.zeros(s.shape, s.dtype), shapes)
            start = self._projected_start(ctx, *self._continued_or_constant(ctx, record, warm))
        else:
            seed = jax.lax.cond(
                record.fresh, lambda: self.cold_seed(ctx, *cold_inputs)[0], lambda: warm
            )
            hidden = jnp.where(record.fresh, seed[0], record.theta)
            start = self._projected_start(
                ctx, functools.partial(ctx.basis.evaluate, seed[0]), seed[1]
            )
        warm_used = ~record.fresh
        return Seed((hidden, start), warm_used, jnp.array(False), restart_history=record.history)

    def _projected_start(self, ctx: StepContext, curve, p1):
        """The projected step's start as `solve_projected` takes it: the curve projected on
        the step's span, with `p1` the start of `p_{n+1}`."""
        return lambda span: self.formulation.start(curve, p1, span, ctx)

    def _continued_or_constant(self, ctx: StepContext, record: SeedRecord, warm):
        """The start of a projected step: the previous step's curve continued, or on the
        first step the constant curve `q_n` with `p_{n+1} = p_n`."""
        theta, p1 = warm
        p1 = jnp.where(record.fresh, ctx.p0, p1)
        nodes = self.formulation_nodes(ctx)
        matrices = ctx.basis.sample_matrices(np.concatenate([nodes, [0.0, 1.0]]))
        if matrices is not None:  # a product with constants, not the basis evaluated
            dtype = ctx.q0.dtype
            values, slopes = (jnp.asarray(m, dtype) @ theta for m in matrices)
            r = len(nodes)
            values = jnp.where(record.fresh, ctx.q0, values)
            slopes = jnp.where(record.fresh, 0, slopes).astype(dtype)
            return CurveSamples(values[:r], slopes[:r], values[r:]), p1

        def curve(tau):
            return jnp.where(record.fresh, ctx.q0, ctx.basis.evaluate(theta, tau))

        return curve, p1

    def _warm_seed(self, ctx: StepContext, record: SeedRecord):
        """The previous step's curve continued over this step, and its end momentum."""
        ratio = ctx.h / record.h_prev
        theta = ctx.basis.advance(record.theta, ratio)  # unused on a `fresh` record
        q1, dq1 = ctx.basis.value_and_derivative(theta, jnp.ones((), ctx.q0.dtype))
        p1 = ctx.term.momentum(ctx.t + ctx.h, q1, dq1 / ctx.h, ctx.args)
        return jax.lax.stop_gradient((theta, p1))

    def _warm_acceptable(self, warm, ctx: StepContext, record: SeedRecord, made_jump):
        """Whether the warm start's residual passes `PreviousStep`'s acceptance test."""
        residual = jax.tree_util.tree_leaves(self.formulation.residual(warm, ctx))
        fmax = jnp.max(jnp.stack([jnp.max(jnp.abs(r)) for r in residual]))
        tolerance = self.initial_trajectory.accept_tolerance(ctx.q0.dtype)
        used = ~record.fresh & (fmax <= tolerance * residual_scale(ctx))
        if made_jump is not False:
            used = used & ~made_jump
        return used

    def _refit_allowed(self, ctx: StepContext, last_residual, last_iterations):
        """Whether the previous step's root is fit to refit from: its solve ended at a
        residual of at most `refit_residual` (relative to the residual scale) and took at most
        `refit_iterations` iterations. Roots left at a higher residual, or reached only
        slowly, are ill-conditioned, and refits carried on from them drift into worse ones,
        step after step."""
        allowed = jnp.array(True)
        if self.policy.refit_residual is not None:
            allowed = last_residual <= self.policy.refit_residual * residual_scale(ctx)
        if self.policy.refit_iterations is not None:
            allowed = allowed & (last_iterations <= self.policy.refit_iterations)
        return allowed

    # -- fits of the trajectory seed ---------------------------------------------------------
    def _fit_inputs(self, ctx: StepContext, previous, fresh, history):
        """What a seed fit needs: the fit problem for the trajectory seed's labels (with the
        previous step's parameters `previous`, unused on a `fresh` start), and the labels'
        end position and momentum."""
        labels, p_end = self.initial_trajectory.labels(
            ctx.term, ctx.t, ctx.h, ctx.q0, ctx.p0, ctx.args, history
        )
        targets, modulated = self.formulation.fit_targets(labels, ctx.q0)
        # The seed is a starting point, not part of the solution: no derivative flows through
        # it (and none may, through the while loop of `diffrax_vi._lazy.unless_all_skip`).
        targets, previous, q_end, p_end = jax.lax.stop_gradient(
            (targets, previous, labels[-1], p_end)
        )
        return fit_problem(targets, modulated, previous, fresh), q_end, p_end

    def _fresh_seed(self, ctx: StepContext, inputs):
        """The seed from a fresh fit (`initial_guess`) of the trajectory seed."""
        problem, q_end, p_end = inputs
        theta = self.policy.initial_guess.parameters(ctx.basis, problem)
        return jax.lax.stop_gradient(self.formulation.unknowns(theta, q_end, p_end))

    def cold_seed(
        self, ctx: StepContext, previous, fresh, history, lazy: bool = False, refit_ok=True
    ):
        """The seed from a trajectory fit, whether it reused the previous step's neurons
        `previous` (`refits`; never on a `fresh` start, nor where `refit_ok` is false), and
        the fit's inputs. With `lazy`, a refit that is not reused is returned as it is: the
        caller starts from the fresh fit instead."""
        inputs = self._fit_inputs(ctx, previous, fresh, history)
        if not self.refits:
            return self._fresh_seed(ctx, inputs), jnp.array(False), inputs
        problem, q_end, p_end = inputs
        theta, misfit = refit_output_weights(ctx.basis, problem)
        tolerance = self.policy.refit_tolerance
        if tolerance is None:
            tolerance = float(jnp.finfo(ctx.q0.dtype).eps) ** 0.5
        reused = ~fresh & (misfit <= tolerance) & refit_ok
        x = jax.lax.stop_gradient(self.formulation.unknowns(theta, q_end, p_end))
        if not lazy:
            x = unless_all_skip(~reused, lambda: self._fresh_seed(ctx, inputs), x)
        return x, reused, inputs

    # -- what the solve reads ----------------------------------------------------------------
    def root_find_start(self, seed: Seed):
        """The all-parameter root find's start, the seed part of its `args` (after the step
        context) and its fallback (`StepHints`). The fresh trajectory fit, whose inputs travel in
        the `args`, is the root finder's fallback (with `lazy`): it starts there where the
        carried seed (warm start or refitted neurons) is unusable, and restarts there once
        where the solve from the carried seed fails (`restart_failed`)."""
        restart_inputs = jax.lax.stop_gradient(seed.cold_inputs)
        carried = seed.warm | seed.refitted
        x0 = seed.start
        hints = StepHints()
        if self.lazy:
            restart = self.policy.restart_failed
            hints = StepHints(
                fallback=self.fallback,
                start_at_fallback=lambda a: ~a[2],
                fallback_usable=lambda a: a[2] & restart,
            )
            # The unused seed only gives the shape: keep it finite.
            x0 = jax.tree_util.tree_map(lambda v: jnp.where(carried, v, 0), x0)
        args = (restart_inputs, carried, seed.fit_inputs if self.lazy else None)
        return x0, args, hints

    def fallback(self, args):
        """The fresh seed the root finder starts or restarts from. Its `args` carry the step
        context, the previous step's parameters, `fresh` flag and history, and the fit's
        inputs where the step computed them already (else `None`)."""
        ctx, cold_inputs, _, inputs = args
        if inputs is None:
            inputs = self._fit_inputs(ctx, *cold_inputs)
        else:  # the grid came through `args` traced; the OGA wants it constant
            problem, q_end, p_end = inputs
            inputs = (with_constant_grid(problem), q_end, p_end)
        return self._fresh_seed(ctx, inputs)

    def restart_point(self, ctx: StepContext, span, history):
        """The projected step's restart: the trajectory seed's labels (piecewise linear in
        `τ`) and `p_{n+1}` estimate, as span coordinates."""
        labels, p_end = self.initial_trajectory.labels(
            ctx.term, ctx.t, ctx.h, ctx.q0, ctx.p0, ctx.args, history
        )
        seed_curve = labels_curve(labels.astype(ctx.q0.dtype))
        z = self.formulation.start(seed_curve, p_end.astype(ctx.p0.dtype), span, ctx)
        return jax.lax.stop_gradient(z)


def _history(ctx: StepContext, curve, q1: Array) -> StepHistory:
    """The ends of the converged step, for the next step's Hermite extrapolation."""
    dtype = ctx.q0.dtype
    ends = jnp.array([0.0, 1.0], dtype)
    _, dq = stage_values(curve, ends)
    v = dq / ctx.h
    ts = ctx.t + ends * ctx.h
    qs = jnp.stack([ctx.q0, q1])
    _, f = jax.vmap(ctx.term.momentum_and_force, in_axes=(0, 0, 0, None))(ts, qs, v, ctx.args)
    v, f = v.astype(dtype), f.astype(dtype)
    return jax.lax.stop_gradient(
        StepHistory(jnp.array(True), ctx.t, ctx.h, ctx.q0, v[0], ctx.p0, f[0], v[1], f[1])
    )


def _can_refit(basis: AbstractBasis, initial_guess) -> bool:
    """Refits keep the neurons of an OGA-seeded shallow network and refit its output weights."""
    return isinstance(initial_guess, AbstractOGA) and isinstance(basis, ShallowNetBasis)


def _check_policy(policy: SeedPolicy) -> None:
    """Refuse options of the wrong type or out of range, naming them."""
    if not isinstance(policy.initial_trajectory, AbstractInitialTrajectory):
        raise TypeError(
            "initial_trajectory must be IntegratorExtrapolation(), HermiteExtrapolation(), "
            f"NoExtrapolation() or PreviousStep(); got {policy.initial_trajectory!r}"
        )
    if not isinstance(policy.initial_guess, AbstractParameterSeed):
        raise TypeError(
            "initial_guess must be an OGA configuration (e.g. OGA1d()) or a parameter seed "
            f"(LSGD(), TrainingMethod(), LeastSquaresFit(), ...); got {policy.initial_guess!r}"
        )
    for name in ("restart_failed", "reuse_neurons"):
        if not isinstance(getattr(policy, name), bool):
            raise TypeError(f"{name} must be True or False, got {getattr(policy, name)!r}")
    for name in ("refit_tolerance", "refit_residual"):
        tol = getattr(policy, name)
        if tol is not None and not (
            isinstance(tol, int | float) and not isinstance(tol, bool) and tol >= 0
        ):
            raise ValueError(f"{name} must be None or a number >= 0, got {tol!r}")
        if tol is not None and not policy.reuse_neurons:
            raise ValueError(f"{name} applies to refits: pass it with reuse_neurons=True")
    cap = policy.refit_iterations
    if cap is not None and (not isinstance(cap, int) or isinstance(cap, bool) or cap < 0):
        raise ValueError(f"refit_iterations must be None or an integer >= 0, got {cap!r}")
    if cap is not None and not policy.reuse_neurons:
        raise ValueError("refit_iterations applies to refits: pass it with reuse_neurons=True")


def _check_policy_against(
    policy: SeedPolicy, basis: AbstractBasis, formulation: AbstractFormulation
) -> None:
    """Refuse a policy that does not fit the ansatz or the formulation, naming the option."""
    # The fixed span of the projected step needs no seed fit at all.
    fixed_span = isinstance(formulation, VariableProjection) and isinstance(
        formulation.hidden, UniformLayer
    )
    if not fixed_span:
        policy.initial_guess.check(basis)
    if isinstance(policy.initial_trajectory, PreviousStep):
        if not isinstance(formulation, FreeEndpoints) or not basis.can_advance:
            raise ValueError(
                "PreviousStep continues the previous step's curve past its end, which needs "
                f"FreeEndpoints() and an ansatz that can be continued; {basis!r} with "
                f"{type(formulation).__name__}() cannot. Use IntegratorExtrapolation() or "
                "HermiteExtrapolation()."
            )
    if isinstance(formulation, VariableProjection):
        if policy.all_parameter_only:
            raise ValueError(
                "VariableProjection() carries its hidden layer from step to step by its "
                "`hidden` rule; reuse_neurons and PreviousStep() belong to the all-parameter "
                "formulations"
            )
        if fixed_span and policy.fits_a_seed:
            raise ValueError(
                "VariableProjection() with its fixed UniformLayer() fits no seed, so "
                "initial_guess would have no effect; use hidden=SeedLayer() or "
                "FirstSeedLayer() to seed the hidden layer by a fit, or "
                "formulation=FreeEndpoints() for the all-parameter step"
            )
    if policy.reuse_neurons and not _can_refit(basis, policy.initial_guess):
        raise ValueError(
            "reuse_neurons refits the output weights of a ShallowNetBasis seeded by an OGA "
            f"configuration; got {basis!r} with {policy.initial_guess!r}"
        )
