"""A fixed step that is split where it fails: `RetryFailedSteps`.

A long run with fixed steps ends at its first failed step (`diffrax.ConstantStepSize` has no
way to retry one). An adaptive controller retries, but it also changes the length of the
steps that did not fail, which a variational integrator should not do: the bounded energy
error rests on applying the same map on every step. `RetryFailedSteps` keeps the grid
`t0 + k·dt0` of `ConstantStepSize` and only splits the interval of a failed step into smaller
pieces until they succeed; the next interval is again a full step. A run without failures
takes exactly the steps (and gives exactly the numbers) of `ConstantStepSize`.

A step counts as failed when its end state, or its error estimate where the solver gives one,
is not finite. `NetworkVI` and `CGVI` return a NaN end state on every failed step; diffrax's
implicit Runge–Kutta solvers return an infinite error estimate. Each failed trial is one
rejected step in `sol.stats["num_rejected_steps"]`.
"""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

__all__ = ["RetryFailedSteps"]


class _RetryState(eqx.Module):
    index: Array  # the grid point the current interval ends at (1 … num_steps)
    end: Array  # that grid point's time
    num_steps: Array  # grid intervals in [t0, t1]; -1 when t1 is infinite
    t0: Array
    t1_or_dt0: Array  # t1, or dt0 when t1 is infinite
    piece: Array  # the length of the pieces the current interval is taken in
    splits: Array  # how often the current interval's piece has been shrunk


def _all_finite(tree) -> Array:
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


class RetryFailedSteps(diffrax.AbstractStepSizeController):
    """Constant steps of `dt0`; a step that fails is retried in smaller pieces.

    Where the step over `[t_n, t_n + dt0]` fails, it is tried again over a piece `shrink`
    times as long, then shorter still if that fails too, at most `max_splits` times; once a
    piece succeeds, the rest of the interval is taken in pieces of that length and the run
    goes on with full steps from `t_n + dt0`. Where a piece of `dt0·shrink^max_splits`
    still fails, that failure is kept: the solve ends with the solver's own failure result
    and step report, as it would under `ConstantStepSize`.

    Every step, split or not, is a step of the same integrator, so a symplectic method stays
    symplectic; the map over a split interval differs slightly from the others, so the
    energy error may jump there (see the how-to "Choosing", section "Long runs").

    **Arguments:**

    - `shrink`: the factor a piece is shortened by after a failure, in (0, 1). Default 0.5.
    - `max_splits`: how often one interval's piece may be shortened before its failure is
      final. Default 8 (pieces down to `dt0/256`).

    Pass `dt0` to `diffeqsolve` as for `ConstantStepSize`, and a `max_steps` that leaves
    room for the retries (each failed trial and each piece counts as a step).

    Gradients pass through a run with retries (the choice of pieces is not differentiated,
    as with any step-size controller). A failed `NetworkVI` trial adds nothing to them: its
    NaN end state is a constant. A vector field that itself produces the NaN (a square root
    of a negative number, say) must make it a constant branch of a `jnp.where`, with the
    other branch fed only valid inputs, as anywhere in JAX; otherwise the rejected trial's
    NaN derivative reaches the gradient.
    """

    shrink: float = 0.5
    max_splits: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        shrink = self.shrink
        if isinstance(shrink, bool) or not isinstance(shrink, (int, float)) or not (
            0 < shrink < 1
        ):
            raise ValueError(f"shrink must be a number in (0, 1), got {shrink!r}")
        splits = self.max_splits
        if isinstance(splits, bool) or not isinstance(splits, int) or splits < 0:
            raise ValueError(f"max_splits must be a non-negative integer, got {splits!r}")

    def wrap(self, direction):
        return self

    def init(
        self,
        terms: PyTree,
        t0,
        t1,
        y0,
        dt0,
        args,
        func: Callable,
        error_order,
    ):
        del terms, y0, args, func, error_order
        if dt0 is None:
            raise ValueError(
                "RetryFailedSteps needs the step: pass dt0 to diffeqsolve (it sets the grid "
                "t0 + k*dt0, as for ConstantStepSize)"
            )
        t0 = jnp.asarray(t0)
        num_steps = jnp.ceil((t1 - t0) / eqxi.nextafter(dt0)).astype(jnp.int32)
        num_steps = jnp.where(jnp.isfinite(t1), num_steps, -1)
        t1_or_dt0 = jnp.where(jnp.isfinite(t1), t1, dt0)
        time_dtype = jnp.result_type(t0, t1_or_dt0)
        state = _RetryState(
            index=jnp.array(1, jnp.int32),
            end=(t0 + dt0).astype(time_dtype),
            num_steps=num_steps,
            t0=t0.astype(time_dtype),
            t1_or_dt0=jnp.asarray(t1_or_dt0, time_dtype),
            piece=jnp.asarray(dt0, time_dtype),
            splits=jnp.array(0, jnp.int32),
        )
        return t0 + dt0, state

    def _next_end(self, state: _RetryState):
        """The grid point after `state.end`, computed as `ConstantStepSize` computes it (a
        fraction of the span, `t1` itself at the last; `end + dt0` on an open span), so that
        a run without failures takes the very same times."""
        dtype = state.t1_or_dt0.dtype
        index = state.index + 1
        fraction = index.astype(dtype) / state.num_steps.astype(dtype)
        point = state.t0 + (state.t1_or_dt0 - state.t0) * fraction
        point = jnp.where(index == state.num_steps, state.t1_or_dt0, point)
        return jnp.where(state.num_steps >= 0, point, state.end + state.t1_or_dt0)

    def adapt_step_size(
        self,
        t0,
        t1,
        y0,
        y1_candidate,
        args,
        y_error,
        error_order,
        controller_state: _RetryState,
    ):
        del y0, args, error_order
        state = controller_state
        ok = _all_finite(y1_candidate) & _all_finite(y_error)
        final = ~ok & (state.splits >= self.max_splits)
        keep = ok | final
        dtype = state.piece.dtype
        end = state.end
        # Within a tolerance of the grid point counts as there: pieces add up with rounding.
        reached = t1 >= end - 4 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(end), 1)
        advance = keep & reached
        next_end = jnp.where(advance, self._next_end(state), end)
        piece = jnp.where(
            keep, jnp.where(reached, next_end - end, state.piece), self.shrink * (t1 - t0)
        )
        splits = jnp.where(advance, 0, jnp.where(keep, state.splits, state.splits + 1))
        next_t0 = jnp.where(keep, t1, t0)
        # Full steps land on the grid exactly; a piece stops at the interval's end.
        next_t1 = jnp.where(advance, next_end, jnp.minimum(next_t0 + piece, next_end))
        new_state = _RetryState(
            index=jnp.where(advance, state.index + 1, state.index),
            end=next_end.astype(dtype),
            num_steps=state.num_steps,
            t0=state.t0,
            t1_or_dt0=state.t1_or_dt0,
            piece=piece.astype(dtype),
            splits=splits,
        )
        return keep, next_t0, next_t1, False, new_state, diffrax.RESULTS.successful
