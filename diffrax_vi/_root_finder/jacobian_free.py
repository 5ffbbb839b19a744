"""`JacobianFreeIteration`: a step's equations solved by updates with a constant matrix,
for a system whose Jacobian is that matrix but for terms that change slowly.

The projected step of a Lagrangian with a constant kinetic matrix is such a system: its
equations are linear in the curve's coordinates but for the forces at the nodes, so the
update `z ← z − K⁻¹ F(z)` with `K` the kinetic part of the Jacobian (constant) moves the curve
to where the forces of the last curve put it: Picard's iteration on the forces, as in
IRKGL16. It needs no Jacobian and no factorisation, and contracts at a rate of order `(hω)²`
for a motion of frequency `ω`. The formulation supplies the update (the hint `update`,
`_step.jacobian_free.engine_hints`); this module owns the loop and its stopping rules.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .._lazy import unless_all_skip
from .._linalg import elimination_solve
from .._results import lookup
from .step_hints import AbstractStepRootFinder, hints_of

__all__ = ["AHEAD_MARGIN", "FLOOR_DELAY", "JacobianFreeIteration", "JacobianFreeState",
           "MAX_GROWTH", "MAX_UPDATES", "NOISE", "PREDICT_MARGIN"]

# Updates at most before the iteration gives up.
MAX_UPDATES = 40
# Stop once the predicted remaining change of the unknowns is below 1/PREDICT_MARGIN of a
# rounding unit of them (relative to their largest value).
PREDICT_MARGIN = 1024
# A change within NOISE rounding units is rounding noise: once the changes stop shrinking
# there, the iteration is at round-off.
NOISE = 64
# Stop after an update whose remaining error, predicted from the updates before it, is below
# 1/AHEAD_MARGIN of a rounding unit (`_iterate`).
AHEAD_MARGIN = 4096
# Updates made after the round-off tests (`PREDICT_MARGIN`, `NOISE`) first pass, before the
# iteration stops on them (`_iterate`).
FLOOR_DELAY = 2
# Consecutive growing updates, above the noise, that end the iteration as not contracting.
MAX_GROWTH = 2


class JacobianFreeState(eqx.Module):
    """How the iteration ended: `f`, the residual's size at the last update (a vector of one,
    as the other root finders keep their residual); the updates made; whether it converged;
    how it failed where it did not (0: a value not finite, 1: the changes grew, 2: too many
    updates); whether the fallback root finder took over."""

    f: Array
    iterations: Array
    converged: Array
    failure: Array
    restarted: Array


class JacobianFreeIteration(AbstractStepRootFinder):
    """Solve `F(z) = 0` by `z ← z + update(z, F(z))` from the start until the change is at
    round-off (predicted from the contraction of the updates before the last, or, a few
    updates after, from the last change or its ceasing to shrink: a stop decided on the last
    change alone would pick iterates by their rounding noise, an energy drift), with a
    constant-matrix update that the caller gives as the hint `update` (and, optionally, a
    cheaper evaluation of the same residual without derivatives as the hint
    `fast_residual`). The whole solve runs in one optimistix step.

    It fails where a value is not finite (`nonfinite`), where the changes grow
    `MAX_GROWTH` times in a row (`nonlinear_divergence`: the iteration does not contract on
    this step) and after `MAX_UPDATES` updates (`nonlinear_max_steps_reached`). With
    `newton_fallback`, a solve that does not converge goes on from the same start by
    Newton's iteration on the same equations (the whole Jacobian by forward derivatives of
    the residual, one column per pass, solved by elimination: no call of a linear-algebra
    library), under the same stopping rules; under `vmap` only where some member needs
    it.

    The root finders with `picard=True` (the defaults of `CGVI` and of the projected
    `NetworkVI`) take this one wherever the step offers the update; it is not meant to be
    given alone.
    """

    hints_read: ClassVar[frozenset[str]] = frozenset(
        {"scale", "max_iterations", "update", "fast_residual"}
    )

    newton_fallback: bool = eqx.field(static=True, default=False)
    rtol: float | None = None
    atol: float | None = None
    norm: Callable = optx.max_norm

    def was_restarted(self, state: JacobianFreeState) -> Array:
        return state.restarted

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, args, f_struct, aux_struct, tags
        if hints_of(options).update is None:
            raise ValueError("JacobianFreeIteration needs the hint `update` (the step's "
                             "constant-matrix update); this step offers none")
        dtype = y[1].dtype
        zero = jnp.array(0, jnp.int32)
        no = jnp.array(False)
        return JacobianFreeState(jnp.full((1,), jnp.inf, dtype), zero, no, zero, no)

    def step(self, fn, y, args, options, state, tags):
        hints = hints_of(options)
        residual = hints.fast_residual or fn

        def evaluate(z):
            return residual(z, args)

        def correction(z, r):
            return hints.update(z, r, args)

        end = _iterate(y, evaluate, correction)
        solved = _ended(end, y, jnp.array(False))
        if not self.newton_fallback:
            return solved[0], solved[1], end.f
        z, state, f = unless_all_skip(
            ~solved[1].converged,
            lambda: self._newton(fn, y, args, solved[1]),
            (*solved, end.f),
        )
        return z, state, f

    @staticmethod
    def _newton(fn, y, args, first: JacobianFreeState):
        """Newton's iteration from the start `y`, counting the updates made before it."""
        _, unravel = ravel_pytree(y)

        def flat_residual(x):
            return ravel_pytree(fn(unravel(x), args)[0])[0]

        def correction(z, r):
            jacobian = _columnwise_jacobian(flat_residual, ravel_pytree(z)[0])
            return unravel(-elimination_solve(jacobian, ravel_pytree(r)[0]))

        end = _iterate(y, lambda z: fn(z, args), correction)
        z, state = _ended(end, y, jnp.array(True))
        state = eqx.tree_at(lambda s: s.iterations, state, state.iterations + first.iterations)
        return z, state, end.f

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        # one lookup: converged, or the failure's code (a chain of `where`s is one
        # instruction each in every compiled step)
        code = jnp.where(state.converged, 3, state.failure)
        value = lookup(_RESULT_OF_CODE, code)
        return jnp.array(True), eqx.tree_at(lambda r: r._value, optx.RESULTS.successful, value)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


# the optimistix result of each failure code (0 not finite, 1 growing, 2 too many updates)
# and of convergence (3)
_RESULT_OF_CODE = np.array([int(r._value) for r in (
    optx.RESULTS.nonfinite, optx.RESULTS.nonlinear_divergence,
    optx.RESULTS.nonlinear_max_steps_reached, optx.RESULTS.successful)], np.int32)


def _ended(end, y, restarted) -> tuple[tuple[Array, Array], JacobianFreeState]:
    """The unknowns and the state at the end of `_iterate`."""
    k = y[0].shape[0]
    stats = end.stats
    failure = jnp.where(jnp.isfinite(stats[_CHANGE]),
                        jnp.where(stats[_GROWTH] > MAX_GROWTH, 1, 2), 0)
    state = JacobianFreeState(stats[_RESIDUAL][None], stats[_UPDATES].astype(jnp.int32),
                              stats[_CONVERGED] != 0, failure.astype(jnp.int32), restarted)
    return (end.x[:k], end.x[k]), state


def _columnwise_jacobian(fn, x: Array) -> Array:
    """`∂fn/∂x` one column per pass of a loop (a forward derivative along each axis).
    `jax.jacfwd` would batch the derivatives, and XLA's CPU backend compiles the batched
    products of a span of more than a few directions as calls of its dot library, which keep
    the solve's loop from being compiled whole (`linalg.elimination_solve`)."""
    n = x.shape[0]
    out = jax.eval_shape(fn, x)

    def column(i, jacobian):
        _, derivative = jax.jvp(fn, (x,), ((jnp.arange(n) == i).astype(x.dtype),))
        return jax.lax.dynamic_update_slice(jacobian, derivative[:, None], (0, i))

    return jax.lax.fori_loop(0, n, column, jnp.zeros((out.shape[0], n), out.dtype))


class _Carry(NamedTuple):
    """The iteration's state, packed so that an update writes three arrays (each array a
    loop carries is at least one kernel of its own per update, scalars included): the
    unknowns `x = [δc; Δp]` (`(k + 1) × D`), the residual's auxiliary output `f` (the forces
    at the nodes), and `stats`, the scalars of the stopping rules in the order of `_STATS`,
    stored in the unknowns' dtype (counts and flags are small integers, exact in any
    float)."""

    x: Array
    f: Array
    stats: Array


_STATS = ("change", "rate", "residual", "growth", "updates", "converged", "done", "floor")
_CHANGE, _RATE, _RESIDUAL, _GROWTH, _UPDATES, _CONVERGED, _DONE, _FLOOR = range(len(_STATS))


def _iterate(z0, residual, correction) -> _Carry:
    """`z ← z + correction(z, r)` from `z0 = (δc, Δp)` until the change is at round-off
    (predicted or seen), growing, not finite, or `MAX_UPDATES` were made; `residual(z)` is
    `((r, c), f)`. Every update is tested."""
    dtype = z0[1].dtype
    eps = float(jnp.finfo(dtype).eps)
    tiny = float(jnp.finfo(dtype).tiny)
    k = z0[0].shape[0]

    def update(c: _Carry) -> _Carry:
        z = (c.x[:k], c.x[k])
        (r, cont), f = residual(z)
        dc, dp = correction(z, (r, cont))
        dx = jnp.concatenate([dc, dp[None]])
        x = c.x + dx
        # the three sizes the tests need, in one kernel
        delta, size, fsize = _max_abs(jnp.stack([dx, x, jnp.concatenate([r, cont[None]])]))
        last = c.stats
        change = delta / jnp.maximum(size, tiny)
        known = jnp.isfinite(last[_CHANGE]) & (last[_CHANGE] > 0)
        rate = change / jnp.where(known, last[_CHANGE], 1)
        # the worse of the last two rates: the error has several modes, and a ratio taken as
        # a fast one dies out understates the slow one's (stopping one update early leaves an
        # error of the same sign on every step, an energy drift)
        worst = jnp.maximum(rate, last[_RATE])
        # Whether to stop after this update is decided on the updates before it: this one's
        # change, at round-off, is mostly the rounding noise of the iterate it made, and
        # stopping on it picks iterates by their noise (stopping when the change looks small
        # keeps iterates whose noise has the sign of the error left before it: an error of
        # one sign on every step, an energy drift). The remaining error after this update is
        # about `change_prev · w² / (1 − w)` with `w` the rate of the update before it.
        ahead = last[_RATE]
        predicted_ahead = (jnp.isfinite(ahead) & (ahead < 1)
                           & (last[_CHANGE] * ahead * ahead <= (1 - ahead) * eps / AHEAD_MARGIN))
        # the tests on this update's change (predicted from it, or at the noise) stop only
        # FLOOR_DELAY updates after they first pass, so that the iterate returned is not the
        # one they picked
        predicted = known & (worst < 1) & (change * worst <= (1 - worst) * eps / PREDICT_MARGIN)
        at_noise = (change <= NOISE * eps) & (change >= 0.5 * last[_CHANGE])
        floor = jnp.where((last[_FLOOR] > 0) | predicted | at_noise, last[_FLOOR] + 1, 0)
        finite = jnp.isfinite(change)
        converged = ((change == 0) | predicted_ahead | (floor > FLOOR_DELAY)) & finite
        growing = (change > NOISE * eps) & (change >= last[_CHANGE])
        growth = jnp.where(growing, last[_GROWTH] + 1, 0)
        updates = last[_UPDATES] + 1
        done = converged | ~finite | (growth > MAX_GROWTH) | (updates >= MAX_UPDATES)
        # one array, so that the scalars are one fused kernel rather than one each
        stats = jnp.stack([change, jnp.where(known, rate, jnp.inf), fsize, growth, updates,
                           converged, done, floor]).astype(dtype)
        return _Carry(x, f, stats)

    stats = np.zeros(len(_STATS))
    stats[[_CHANGE, _RATE, _RESIDUAL]] = np.inf
    f0 = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype),
                                jax.eval_shape(lambda: residual(z0)[1]))
    carry = _Carry(jnp.concatenate([z0[0], z0[1][None]]), f0, jnp.asarray(stats, dtype))
    return jax.lax.while_loop(lambda c: c.stats[_DONE] == 0, update, carry)


def _max_abs(x: Array) -> Array:
    """`max |x|` over all axes but the first, by halving elementwise maxima: a reduction of
    these sizes costs far more as a reduction kernel (alone and under `vmap`) than as a
    few fused elementwise operations."""
    a = jnp.abs(x.reshape(x.shape[0], -1))
    while a.shape[1] > 1:
        half = a.shape[1] // 2
        top = jnp.maximum(a[:, :half], a[:, half:2 * half])
        a = top if a.shape[1] % 2 == 0 else jnp.concatenate([top, a[:, 2 * half:]], axis=1)
    return a[:, 0]
