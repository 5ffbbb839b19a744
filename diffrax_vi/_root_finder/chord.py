"""A chord (simplified Newton) iteration for the projected step of non-stiff problems.

Two matrices serve: the Jacobian at the start of the solve, or its kinetic part alone
(`matrix="kinetic"`), which needs no derivatives of the forces.

`RoundoffNewton` forms and factorises a fresh Jacobian on every iteration. When the start is
already close to the root (the previous step's curve continued, on a non-stiff problem), the
Jacobian hardly changes during a solve, and the fixed-point iteration

    z ← z − J₀⁻¹ F(z),    J₀ the Jacobian at the start of the solve,

converges linearly with a small contraction factor: each iteration costs one residual and a
product with `J₀⁻¹` instead of a Jacobian, an LU factorisation and a line search.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .._lazy import unless_all_skip
from .._precision import lapack_dtype
from .newton import NewtonState, RoundoffNewton
from .step_hints import hints_of

__all__ = ["ChordIteration"]

# `predict` stops once the remaining error is below 1/PREDICT_MARGIN of a rounding unit of the
# unknowns: small against the rounding of a step (about 0.4 eps of energy), so that what the
# iteration leaves behind cannot build up to a drift.
PREDICT_MARGIN = 1024

# An update within this many rounding units of the largest unknown is taken as rounding noise
# by `predict`: its ratio to the update before it says nothing about the iteration's rate.
NOISE_UPDATE = 4

# The `refresh` of the updates after a restart (`ChordIteration._second_try`).
SECOND_TRY_REFRESH = 0.5


class _ChordState(NewtonState):
    factors: tuple[Array, ...]
    contraction: Array
    refreshes: Array
    fresh: Array
    due: Array  # `factors` are to be formed afresh at the point before the next update


def _factor(jac: Array, dtype, inverse: bool) -> tuple[Array, ...]:
    """`(J⁻¹,)` or the LU factors `(lu, pivots)` of `jac`, in the working precision (float32
    below 32 bits)."""
    lu = jax.scipy.linalg.lu_factor(jac.astype(lapack_dtype(dtype)))
    if not inverse:
        return lu
    eye = jnp.eye(jac.shape[0], dtype=lu[0].dtype)
    return (jax.scipy.linalg.lu_solve(lu, eye),)


def _apply(factors: tuple[Array, ...], f: Array) -> Array:
    """`J⁻¹ f` from `_factor`'s output, in the dtype of `f`."""
    work = factors[0].dtype
    if len(factors) == 1:
        out = factors[0] @ f.astype(work)
    else:
        out = jax.scipy.linalg.lu_solve(factors, f.astype(work))
    return out.astype(f.dtype)


class ChordIteration(RoundoffNewton):
    """The chord iteration `z ← z − J₀⁻¹ F(z)` for a square system, run to round-off.

    The Jacobian (the hint `jacobian` where the caller gives one, else `jax.jacfwd`) is
    formed and LU-factorised once, at the start of the solve; every iteration then costs one
    residual and one application of the factors. Where the caller gives the hint `inverse`
    (the projected step's elimination without pivoting, cheaper than LAPACK at its sizes),
    the start takes that explicit inverse instead (with `pivoted_fallback`, the
    factorisation where it is not finite). It converges linearly, at a rate that is
    small when
    the start is close to the root and the Jacobian varies little along the way: a non-stiff
    problem solved from the previous step's curve. A drop-in for `RoundoffNewton` wherever
    the solver accepts one (`CGVI`, the projected `NetworkVI` step).

    Stopping rules are those of `RoundoffNewton`: converged at `max|F| ≤ ftol · eps · scale`
    after an update within `√eps` of the unknowns (`confirm`), or at round-off once
    `max|F| ≤ floor · eps · scale` and the update has stopped shrinking (`ftol=0` runs every
    solve there); and one more (`predict`): at round-off once the contraction of the
    updates predicts that what is left is far below one rounding unit of the unknowns.
    Every solve makes at least one update. There is no line
    search: each update is taken. An iteration far from the root (above `floor`) whose
    residual does not fall, or whose update is no smaller than the one before, is a stall;
    `max_stalls` stalls in a row end the solve as `nonlinear_divergence`, a non-finite
    residual as `nonfinite`, so an iteration that cannot contract (a stiff problem, a long
    step) fails loudly and the step is rejected rather than accepted wrong.

    The hints `max_iterations` and `restart = (first_try, start)` have the meaning they
    have for `RoundoffNewton`. With `restart=True` the iteration's matrix is formed and
    factorised afresh at the restart point, and (with `matrix="jacobian"`) the updates after
    it refresh their Jacobian as `refresh=0.5` does: where the chord iteration could not
    contract from the first start (a stiff problem, a long step), the second try is
    Newton's method, at Newton's price, instead of a second failure. Without it (the
    default) such a step fails, for the step-size controller to retry.

    **Arguments:**

    - `ftol`, `floor`, `confirm`, `max_stalls`: as for `RoundoffNewton` (defaults 64, 4096,
      `True`, 3).
    - `refresh`: `None` (default) keeps the start's Jacobian for the whole solve. A number
      `ρ` in `(0, 1)` forms and factorises the Jacobian again at the current point whenever,
      far from the root, the update shrank by less than `ρ` (the estimated contraction
      factor `‖Δz_k‖ / ‖Δz_{k−1}‖ > ρ`), or stalled (then the update is undone first). An
      update from a Jacobian formed where it starts is Newton's, with `RoundoffNewton`'s
      backtracking far from the root: on a harder problem the iteration turns into Newton's
      method instead of failing.
    - `inverse`: apply the factors as the explicit inverse `J₀⁻¹` (default `True`: one small
      matrix-vector product per iteration, where a pair of triangular solves costs more than
      the residual at the sizes of a step) or by triangular solves (`False`). The fixed point
      is the root either way; only the contraction factor sees the inverse's rounding.
    - `matrix`: the matrix of the iteration. `"jacobian"` (default): the Jacobian at the
      start, as above. `"kinetic"`: the Jacobian of the kinetic part alone, for a Lagrangian
      `½ vᵀ M v` with `M = ∂²L/∂v²` averaged over the nodes of the start
      (`VariableProjection.kinetic_inverse`; only the projected step supplies it). It needs
      no derivative of the forces and, where the span is the same in every coordinate
      (`CGVI`, the default network step), costs one small inverse per coordinate block:
      cheap for many coordinates. It contracts at a rate of order `(hω)²` for a motion of
      frequency `ω`, and slower where `M` or the forces depend on the velocities. It needs
      `M` invertible (a regular Lagrangian); a degenerate one fails the step. With `refresh`,
      a slow or stalled update switches the solve to the full Jacobian (Newton's update).
      Give it `ftol=0`: a linearly converging iteration stopped at a tolerance leaves an
      error of about that tolerance that is a fixed function of the state, a bias that
      `confirm` cannot remove, and the energy drifts (see the benchmarks page).
    - `predict`: also converge once the contraction factor `θ` (the larger of the last two
      ratios of successive updates) predicts a remaining error `θ/(1 − θ)·max|Δz|` below
      `1/1024` of a rounding unit of the unknowns, with the residual within `floor`: the
      round-off limit in about half the updates of `ftol=0` alone. Those updates are not
      all idle: over many spans, a solve ended this early keeps a small mean energy bias
      that one run to round-off does not (the benchmarks page). An update within a few
      rounding units of the unknowns is rounding noise, whose ratio to the update before
      says nothing of the rate: there the ratio before it is the rate, and the noise's size
      the update. Never after the first update. Default `False`.
    - `picard`, `picard_fallback`, `restart`, `pivoted_fallback`: as for `RoundoffNewton`
      (the Jacobian-free iteration where it fits, default `False`, `CGVI`'s default sets
      it; no fallback of either kind and no restart inside the step by default).
    - `max_backtracks`: halvings of a Newton update with `refresh` (default 20).
    - `rtol`, `atol`, `norm`: unused (inherited).

    The root finder's final state holds `contraction` (the last contraction estimate) and
    `refreshes` (the Jacobians formed after the first).
    """

    hints_read: ClassVar[frozenset[str]] = frozenset(
        {"scale", "jacobian", "inverse", "max_iterations", "restart", "kinetic"}
    )

    refresh: float | None = eqx.field(static=True, default=None)
    inverse: bool = eqx.field(static=True, default=True)
    matrix: str = eqx.field(static=True, default="jacobian")
    predict: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.matrix not in ("jacobian", "kinetic"):
            raise ValueError(f"matrix must be 'jacobian' or 'kinetic', got {self.matrix!r}")
        for name in ("inverse", "predict"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.refresh is not None and not (
            isinstance(self.refresh, int | float) and not isinstance(self.refresh, bool)
            and 0 < self.refresh < 1
        ):
            raise ValueError(f"refresh must be None or a number in (0, 1), got {self.refresh!r}")

    def _apply(self, factors: tuple, f: Array, y) -> Array:
        """`M⁻¹ f` for the iteration's matrix `M` (flat `f`)."""
        if self.matrix == "jacobian":
            return _apply(factors, f)
        # the projected step's residual `(r, c)` is shaped like its unknowns `(δc, Δp)`
        _, unravel = ravel_pytree(y)
        kinetic = ravel_pytree(factors[0](unravel(f)))[0].astype(f.dtype)
        if len(factors) == 1:
            return kinetic
        return jnp.where(factors[2], _apply(factors[1:2], f), kinetic)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del aux_struct, tags, f_struct
        f, _ = fn(y, args)
        flat = ravel_pytree(f)[0]
        dtype = ravel_pytree(y)[0].dtype
        if self.matrix == "kinetic":
            kinetic = hints_of(options).kinetic
            if kinetic is None:
                raise ValueError(
                    "ChordIteration(matrix='kinetic') needs the kinetic part of the "
                    "Jacobian, which only the projected step supplies (CGVI, or NetworkVI with "
                    "formulation=VariableProjection())"
                )
            factors = (kinetic(y, args),)
            if self.refresh is not None:
                size = flat.shape[0]
                work = lapack_dtype(dtype)
                factors += (jnp.zeros((size, size), work), jnp.array(False))
        else:
            factors = self._start_factors(fn, y, args, options, dtype)
        inf = jnp.full((), jnp.inf, flat.dtype)
        zero = jnp.array(0, jnp.int32)
        no = jnp.array(False)
        return _ChordState(flat, inf, no, no, zero, zero, no, factors,
                           jnp.zeros((), flat.dtype), zero, jnp.array(True), no)

    def _start_factors(self, fn, y, args, options, dtype) -> tuple[Array, ...]:
        """The Jacobian's factors at the start of a solve: the hint `inverse` where the caller
        gives one (an explicit inverse computed its own, cheaper way; with
        `pivoted_fallback`, the pivoted factorisation where that gave non-finite entries);
        else `_factor`."""
        given = hints_of(options).inverse
        jac = self._jacobian(fn, y, args, options)
        if given is None or not self.inverse:
            return _factor(jac, dtype, self.inverse)
        inverse = given(jac, y, args).astype(lapack_dtype(dtype))
        if not self.pivoted_fallback:  # a non-finite inverse fails the solve (`nonfinite`)
            return (inverse,)
        return unless_all_skip(
            ~jnp.all(jnp.isfinite(inverse)), lambda: _factor(jac, dtype, True), (inverse,)
        )

    def _update(self, fn, y, args, options, state):
        """One chord update from `y` (and, with `refresh`, the Jacobian formed again where
        the update was slow or stalled)."""
        flat_y, unravel = ravel_pytree(y)
        dtype = flat_y.dtype
        scale = jnp.asarray(hints_of(options).scale, dtype)
        floor = self._tolerance("floor", dtype) * scale

        def residual(v):
            out, aux = fn(unravel(v), args)
            return ravel_pytree(out)[0], aux

        if self.refresh is not None:
            # Each iteration pays for its test only: the refactorisation, where the update
            # before found it due (or a restart), is a lazy branch.
            factors = self._refactored(state.due, fn, y, args, options, state.factors, dtype)
            state = dataclasses.replace(state, factors=factors, due=jnp.array(False))
        d = -self._apply(state.factors, state.f, y)
        f_new, aux = residual(flat_y + d)
        a = jnp.ones((), dtype)
        if self.refresh is not None:
            a, f_new, aux = self._backtrack(residual, flat_y, d, state, a, f_new, aux, floor)
        new = flat_y + a * d
        # the sizes the tests below need, in one reduction (one kernel in the loop)
        fmax, fmax_new, norm, size = jnp.max(
            jnp.abs(jnp.stack([state.f, f_new, a * d, new])), axis=1
        )
        near = fmax <= floor
        lower = fmax_new <= (1 - 1e-4 * a) * fmax
        iterations = state.iterations + 1
        known = jnp.isfinite(state.step_norm) & (state.step_norm > 0)
        contraction = jnp.where(known, norm / jnp.where(known, state.step_norm, 1), 0)
        # Far from the root a contracting iteration lowers the residual and shrinks its
        # update (a Newton step of the refreshing variant need only lower the residual);
        # `max_stalls` stalls in a row end the solve.
        shrank = norm < state.step_norm
        if self.refresh is not None:
            shrank = shrank | state.fresh
        stalled = ~near & ~(lower & shrank)
        stalls = jnp.where(stalled, state.stalls + 1, 0)
        step_norm = norm
        # (without `refresh` nothing reads `fresh`: passed on as it is, it costs no copy)
        fresh = state.fresh if self.refresh is None else jnp.array(False)
        factors, refreshes = state.factors, state.refreshes
        need = None
        if self.refresh is not None:
            # A stalled chord update is undone and Newton's step taken from where the
            # iteration stood; a slow one is kept, and the next starts from a fresh Jacobian.
            chord_stall = stalled & ~state.fresh
            slow = ~near & ~stalled & (contraction > self.refresh)
            undo = stalled
            new = jnp.where(undo, flat_y, new)
            f_new = jnp.where(undo, state.f, f_new)
            fmax_new = jnp.where(undo, fmax, fmax_new)
            step_norm = jnp.where(undo, state.step_norm, norm)
            stalls = jnp.where(chord_stall, state.stalls, stalls)
            need = chord_stall | slow
            fresh = state.fresh & undo
        converged = fmax_new <= self._tolerance("ftol", dtype) * scale
        if self.confirm:
            converged = converged & (norm <= float(jnp.finfo(dtype).eps) ** 0.5 * size)
        if self.predict:
            converged = converged | self._predicted(
                state, contraction, known, norm, size, fmax_new <= floor, dtype
            )
        # Rounding has taken over once an update near the root is no smaller than the one
        # before it.
        at_floor = near & (norm >= state.step_norm) & (fmax_new <= floor)
        due = state.due
        if need is not None:
            # formed at the start of the next update (`due`)
            due = need & ~(converged | at_floor)
            refreshes = refreshes + due.astype(jnp.int32)
            fresh = fresh | due
        state = _ChordState(f_new, step_norm, converged, at_floor, stalls, iterations,
                            state.restarted, factors, contraction, refreshes, fresh, due)
        return unravel(new), state, aux

    def _backtrack(self, residual, flat_y, d, state, a, f_new, aux, floor):
        """`(a, F, aux)` of the update `a d`: a step with a Jacobian formed where it starts
        is Newton's, and far from the root it halves `a` as `RoundoffNewton` does until the
        residual falls."""
        fmax = jnp.max(jnp.abs(state.f))
        near = fmax <= floor

        def cond(carry):
            a, f_try, _, k = carry
            enough = jnp.max(jnp.abs(f_try)) <= (1 - 1e-4 * a) * fmax
            return state.fresh & ~near & ~enough & (k < self.max_backtracks)

        def body(carry):
            a, _, _, k = carry
            a = a / 2
            f_try, aux = residual(flat_y + a * d)
            return a, f_try, aux, k + 1

        a, f_new, aux, _ = jax.lax.while_loop(cond, body, (a, f_new, aux, 0))
        return a, f_new, aux

    @staticmethod
    def _predicted(state, contraction, known, norm, size, within_floor, dtype) -> Array:
        """Whether the contraction of the updates predicts the remaining error far below one
        rounding unit of the unknowns (`predict`).

        A linear iteration's remaining error is about `θ/(1 − θ)` times its last update (θ
        the contraction factor). It is a fixed function of the step's start, the same from
        step to step: stop only once it is far below one rounding unit of the unknowns
        (`PREDICT_MARGIN`), or it would add up to a drift over a long run. θ is the larger
        of the last two ratios of updates: from a poor start the update after Newton's first
        can shrink far more than the iteration's rate."""
        rate = jnp.maximum(contraction, state.contraction)
        slowing = known & (rate < 1)
        remaining = rate / jnp.where(slowing, 1 - rate, 1) * norm
        eps = float(jnp.finfo(dtype).eps)
        # An update at the rounding noise has a ratio of noise to signal, not the rate:
        # there the rate is the ratio before it, and what is left is that rate times
        # the noise's size (or less).
        noise = NOISE_UPDATE * eps * size
        earlier = state.contraction
        at_noise = (norm <= noise) & (earlier > 0) & (earlier < 1)
        remaining = jnp.where(
            at_noise, jnp.minimum(remaining, earlier / (1 - earlier) * noise), remaining
        )
        return (slowing | at_noise) & within_floor & (remaining <= eps / PREDICT_MARGIN * size)

    def _refactored(self, need, fn, point, args, options, factors, dtype
                    ) -> tuple[Array, ...]:
        """The iteration's factors formed again at `point` where `need` says so (lazy under
        `vmap`): the Jacobian's, or with `matrix="kinetic"` the Jacobian's inverse beside the
        kinetic matrix, which then gives way to it (Newton's update)."""

        def refactor():
            jac = self._jacobian(fn, point, args, options)
            if self.matrix == "kinetic":
                inverse = _factor(jac, dtype, True)[0]
                return (factors[0], inverse, jnp.array(True))
            return _factor(jac, dtype, self.inverse)

        return unless_all_skip(need, refactor, factors)

    def _whole_solve_loop(self, fn, args, options, carry, limit):
        """`RoundoffNewton._whole_solve_loop`; where the updates use only the start's matrix
        (no `refresh`, the Jacobian), the loop carries the unknowns as one flat vector: no
        flattening and unflattening of them on every update."""
        if self.refresh is not None or self.matrix != "jacobian":
            return super()._whole_solve_loop(fn, args, options, carry, limit)
        y, state, aux = carry
        flat, unravel = ravel_pytree(y)
        v, state, aux = super()._whole_solve_loop(
            lambda v, args: fn(unravel(v), args), args, options, (flat, state, aux), limit
        )
        return unravel(v), state, aux

    def _loop_constants(self) -> tuple[str, ...]:
        """Without `refresh`, the updates keep the start's matrix and its bookkeeping."""
        if self.refresh is None:
            return ("restarted", "factors", "refreshes", "fresh", "due")
        return super()._loop_constants()

    def _second_try(self) -> ChordIteration:
        """After a restart, the Jacobian's chord iteration goes on with `refresh`
        (`SECOND_TRY_REFRESH` where none is set): an iteration that did not contract from
        the first start turns into Newton's method from the second instead of failing
        again."""
        if self.matrix == "jacobian" and self.refresh is None:
            return dataclasses.replace(self, refresh=SECOND_TRY_REFRESH)
        return self

    def _restarted(self, fn, start, args, options, carry):
        """`carry` moved to the point `start`, with fresh bookkeeping and the iteration's
        matrix formed and factorised there: the Jacobian's by the first update after it
        (`due`: the updates after a restart refresh, `_second_try`), so that the compiled
        solve holds one copy of its refactorisation, not two."""
        point, newton, aux = super()._restarted(fn, start, args, options, carry)
        state = carry[1]
        dtype = newton.f.dtype
        due = jnp.array(False)
        if self.matrix == "kinetic" and self.refresh is None:
            factors = (hints_of(options).kinetic(point, args),)
        elif self.matrix == "kinetic":
            # with `refresh`, the restart goes on with Newton's update, as a refresh does
            jac = self._jacobian(fn, point, args, options)
            factors = (state.factors[0], _factor(jac, dtype, True)[0], jnp.array(True))
        else:
            factors, due = state.factors, jnp.array(True)
        chord = _ChordState(*(getattr(newton, f.name) for f in dataclasses.fields(newton)),
                            factors, jnp.zeros_like(state.contraction),
                            state.refreshes + 1, jnp.array(True), due)
        return point, chord, aux
