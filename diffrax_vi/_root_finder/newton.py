"""`RoundoffNewton`: Newton's method run to round-off, for a square system with an
isolated root (the projected step's), and the loop that runs a whole solve in one
optimistix step."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .._lazy import unless_all_skip
from .._linalg import solve
from .damped_newton import LevenbergMarquardt
from .step_hints import AbstractStepRootFinder, StepHints, hints_of

__all__ = ["NewtonState", "RoundoffNewton"]


class NewtonState(eqx.Module):
    """Where `RoundoffNewton`'s iteration stands (`ChordIteration`'s state extends it)."""

    f: Array
    step_norm: Array
    converged: Array
    at_floor: Array
    stalls: Array
    iterations: Array
    restarted: Array


class _LoopLayout(eqx.Module):
    """How a root finder's state rides through its loop: the fields its updates never
    change (`constant`) stay outside the loop, and its scalars are stacked as one vector in
    the widest of their floating dtypes, float32 at least, where counts and flags are
    exact."""

    treedef: Any = eqx.field(static=True)
    scalar: tuple[bool, ...] = eqx.field(static=True)
    dtypes: tuple[Any, ...] = eqx.field(static=True)
    work: Any = eqx.field(static=True)
    constant: dict

    @classmethod
    def of(cls, state, constant: tuple[str, ...]) -> _LoopLayout:
        leaves, treedef = jax.tree_util.tree_flatten(
            dataclasses.replace(state, **dict.fromkeys(constant))
        )
        scalar = tuple(jnp.ndim(leaf) == 0 for leaf in leaves)
        dtypes = tuple(jnp.result_type(leaf) for leaf in leaves)
        floats = [d for d, s in zip(dtypes, scalar, strict=True)
                  if s and jnp.issubdtype(d, jnp.floating)]
        work = jnp.result_type(jnp.float32, *floats)
        return cls(treedef, scalar, dtypes, work, {n: getattr(state, n) for n in constant})

    def pack(self, state) -> tuple[list, Array]:
        """The loop's carry of `state`: its other leaves, and its scalars as one vector."""
        leaves = jax.tree_util.tree_leaves(
            dataclasses.replace(state, **dict.fromkeys(self.constant))
        )
        rest = [leaf for leaf, s in zip(leaves, self.scalar, strict=True) if not s]
        packed = jnp.stack([jnp.asarray(leaf).astype(self.work)
                            for leaf, s in zip(leaves, self.scalar, strict=True) if s])
        return rest, packed

    def unpack(self, rest: list, packed: Array):
        """The state from `pack`'s output."""
        rest, leaves, k = iter(rest), [], 0
        for s, dtype in zip(self.scalar, self.dtypes, strict=True):
            if s:
                leaves.append(packed[k] != 0 if dtype == jnp.bool_ else packed[k].astype(dtype))
                k += 1
            else:
                leaves.append(next(rest))
        state = jax.tree_util.tree_unflatten(self.treedef, leaves)
        return dataclasses.replace(state, **self.constant)


class RoundoffNewton(AbstractStepRootFinder):
    """Newton's method for a square system with an isolated root, run to round-off.

    Each iteration solves `J d = −F` by LU with a fresh Jacobian (the hint `jacobian`, a
    function of the unknowns and `args`, where the caller gives one; else `jax.jacfwd`), or
    applies the hint `inverse` (the projected step's inverse by elimination without
    pivoting) where the caller gives one and it is finite. Far
    from the root a backtracking line search halves the step until `max|F|` falls; within
    `floor` of the root the full step is always taken. The solve ends as converged when
    `max|F| ≤ ftol · scale` (the hint `scale`) after an update within `√eps` of the
    unknowns (`confirm`), or when `max|F| ≤ floor · scale` and the Newton update has stopped
    shrinking (rounding has taken over). Quadratic convergence reaches either in a few
    iterations. Every
    solve makes at least one update, whatever the start's residual. It fails
    (`nonlinear_divergence`) after `max_stalls` line searches in a row find no decrease, and
    at the iteration cap.

    Given the hint `max_iterations` (the solver's iteration cap), the whole solve runs in
    one optimistix step, as compiled loops of updates that carry only what the iteration
    needs; `state.iterations` counts the updates. Given also the hint
    `restart = (first_try, start)`, with `restart=True` a solve that has not converged
    after `first_try` iterations (or has stalled or become non-finite before) starts once
    more from
    `start(args)`, within the same cap; the test and the restart sit between two loops,
    not in every iteration, and `start` runs only where a solve needs it (under `vmap`:
    only if some member does). `state.restarted` says whether it did. Without the hint,
    each optimistix step is one update (`optimistix.root_find`'s `max_steps` is the cap).

    **Arguments:**

    - `ftol`: residual for immediate convergence, in units of `eps` of the working dtype
      times the residual scale. Default 64. `0` runs every solve to round-off: it ends only
      once the updates stop shrinking (the rule of `floor`), which removes the bias that
      the first accepted update's rounding leaves (see the benchmarks page on long runs).
    - `floor`: largest residual accepted once the updates stop shrinking, in the same units.
      Default 4096.
    - `confirm`: converge at `ftol` only after an update no larger than `√eps` times the
      unknowns (default `True`). The update that first brings the residual under `ftol`
      starts from the start's error, and the rounding of the iteration matrix leaves a part
      of that error behind which is a fixed linear function of the state: the same bias on
      every step, which makes the energy drift linearly (on the oscillator, thousandths of
      eps per step). One more update, from within `√eps`, shrinks that bias but does not
      remove it on every span; `ftol=0` does (the benchmarks page on long runs). It costs
      about one update per step; `False` skips it.
    - `max_backtracks`: halvings of the step in one line search. Default 20.
    - `max_stalls`: line searches in a row without decrease before giving up. Default 3.
    - `picard`: where the projected step's Lagrangian has a constant kinetic matrix
      `∂²L/∂v²` and its span is known when the step is traced (`CGVI`, a network's fixed
      layer), solve the step by the Jacobian-free iteration on the forces at the nodes
      instead (`_step.jacobian_free`), which needs no Jacobian at all; elsewhere this root
      finder runs as described above. Decided when the step is traced. Default `False`;
      the default root finders of `CGVI` and of the projected `NetworkVI` set it.
    - `picard_fallback`: where the Jacobian-free iteration does not converge, go on with
      Newton's iteration on the same equations from the same start, inside the step.
      Default `False`: such a step fails (`vi_step_stalled`, `vi_step_max_iterations`) and
      the step-size controller recovers it (`RetryFailedSteps` at a constant step,
      `PIDController` with an error estimate), as diffrax's implicit solvers do; the
      fallback roughly doubles the compiled step and slows every step that converges.
    - `restart`: where a solve given the hint `restart` (the projected step from the previous
      curve continued) has not converged after `first_try` iterations, start once more from
      the hint's point (the seed policy's trajectory seed), inside the step. Default
      `False`: such a step fails and the step-size controller recovers it, as with
      `picard_fallback`; the restart more than doubles the compiled step.
    - `pivoted_fallback`: where the formulation's own inverse of the Jacobian (the hint
      `inverse`: elimination without pivoting) is not finite, a pivot having vanished, use
      LAPACK's pivoted LU instead. Default `False`: such an update is not finite and the
      step fails (`nonfinite`) for the step-size controller to retry; the fallback would be
      compiled into every step for a case that needs an exactly singular leading block.
    - `rtol`, `atol`, `norm`: unused; diffrax reads them off the root finder of an implicit
      solver.
    """

    hints_read: ClassVar[frozenset[str]] = frozenset(
        {"scale", "jacobian", "inverse", "max_iterations", "restart"}
    )

    ftol: float = 64.0
    floor: float = 4096.0
    confirm: bool = eqx.field(static=True, default=True)
    max_backtracks: int = eqx.field(static=True, default=20)
    max_stalls: int = eqx.field(static=True, default=3)
    picard: bool = eqx.field(static=True, default=False)
    picard_fallback: bool = eqx.field(static=True, default=False)
    restart: bool = eqx.field(static=True, default=False)
    pivoted_fallback: bool = eqx.field(static=True, default=False)
    rtol: float | None = None
    atol: float | None = None
    norm: Callable = optx.max_norm

    def __check_init__(self):
        for name, least in (("ftol", 0), ("floor", 1e-300)):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and not isinstance(value, bool)
                    and value >= least and math.isfinite(value)):
                kind = "a non-negative" if least == 0 else "a positive"
                raise ValueError(f"{name} must be {kind} number (of eps), got {value!r}")
        for name in ("confirm", "picard", "picard_fallback", "restart", "pivoted_fallback"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.picard_fallback and not self.picard:
            raise ValueError("picard_fallback=True needs picard=True (it is the fallback of "
                             "the Jacobian-free iteration)")
        if self.floor < self.ftol:
            raise ValueError(f"floor ({self.floor}) must be at least ftol ({self.ftol})")
        for name in ("max_backtracks", "max_stalls"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")

    def was_restarted(self, state: NewtonState) -> Array:
        return state.restarted

    def allows_picard(self) -> bool:
        return self.picard

    def picard_falls_back(self) -> bool:
        return self.picard_fallback

    def companion(self) -> optx.AbstractRootFinder:
        # the companion solves all the coefficients of a polynomial: a damped root finder
        return LevenbergMarquardt()

    def _tolerance(self, name: str, dtype) -> float:
        return getattr(self, name) * float(jnp.finfo(dtype).eps)

    @staticmethod
    def _confirmed(norm: Array, y: Array, dtype) -> Array:
        """Whether the last update (`max|Δz| = norm`) is within `√eps` of the unknowns `y`
        (`confirm`)."""
        return norm <= float(jnp.finfo(dtype).eps) ** 0.5 * jnp.max(jnp.abs(y))

    @staticmethod
    def _jacobian(fn, y, args, options) -> Array:
        """The Jacobian at `y`: the hint `jacobian` where the caller gives one, else
        `jax.jacfwd` of the flattened residual."""
        given = hints_of(options).jacobian
        if given is not None:
            return given(y, args)
        flat, unravel = ravel_pytree(y)
        return jax.jacfwd(lambda v: ravel_pytree(fn(unravel(v), args)[0])[0])(flat)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del aux_struct, tags, f_struct
        del options
        f, _ = fn(y, args)
        flat = ravel_pytree(f)[0]
        inf = jnp.full((), jnp.inf, flat.dtype)
        # Never converged at the start: in low precision the tolerance can be as large as the
        # start's residual, and a step must make at least one Newton update.
        no = jnp.array(False)
        return NewtonState(flat, inf, no, no, jnp.array(0, jnp.int32), jnp.array(0, jnp.int32),
                            no)

    def step(self, fn, y, args, options, state, tags):
        del tags
        hints = hints_of(options)
        if hints.max_iterations is None:
            if hints.restart is not None:
                raise ValueError("the hint `restart` needs the hint `max_iterations`")
            return self._update(fn, y, args, options, state)
        return self._whole_solve(fn, y, args, options, state, hints)

    def _whole_solve(self, fn, y, args, options, state, hints: StepHints):
        """The solve from `y` to its end, in compiled loops of `_update`: up to `first_try`
        iterations, the restart where that try ended unconverged, then the rest up to
        `max_iterations`. The restart's test and branch run once per solve, not on every
        iteration; where both tries take the same update, it is compiled once (a loop over
        the tries)."""
        cap = hints.max_iterations
        # the carry's aux before the first update: zeros of its shape (nothing evaluated)
        aux = jax.tree_util.tree_map(
            lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(lambda: fn(y, args)[1])
        )
        carry = (y, state, aux)
        if not self.restart or hints.restart is None or hints.restart[0] >= cap:
            return self._whole_solve_loop(fn, args, options, carry, cap)
        first_try, start = hints.restart

        def restarted(carry, need):
            return unless_all_skip(
                need, lambda: self._restarted(fn, start(args), args, options, carry), carry
            )

        def unconverged(carry):
            state = carry[1]
            return ~(state.converged | state.at_floor) & (state.iterations < cap)

        second = self._second_try()
        if second is not self:
            carry = self._whole_solve_loop(fn, args, options, carry, first_try)
            carry = restarted(carry, unconverged(carry))
            return second._whole_solve_loop(fn, args, options, carry, cap)

        def cond(outer):
            tries, carry = outer
            return (tries == 0) | ((tries == 1) & unconverged(carry))

        def body(outer):
            tries, carry = outer
            carry = restarted(carry, (tries > 0) & unconverged(carry))
            limit = jnp.where(tries > 0, cap, first_try)
            return tries + 1, self._whole_solve_loop(fn, args, options, carry, limit)

        return jax.lax.while_loop(cond, body, (jnp.array(0, jnp.int32), carry))[1]

    def _loop_constants(self) -> tuple[str, ...]:
        """The fields of the state that `_update` never changes (kept out of the loop)."""
        return ("restarted",)

    def _second_try(self) -> RoundoffNewton:
        """The root finder whose updates follow a restart (this one)."""
        return self

    def _whole_solve_loop(self, fn, args, options, carry, limit):
        """`_update` from `carry = (y, state, aux)` until the solve ends or has made `limit`
        updates in all.

        The loop carries the state's scalars (norms, flags, counts) as one small vector, and
        not the fields the updates leave alone (`_loop_constants`): an update then ends in a
        few kernels instead of one for each scalar and its copy, which at the sizes of a
        step cost as much as the residual."""
        y, state, aux = carry
        layout = _LoopLayout.of(state, self._loop_constants())

        def cond(carry):
            state = layout.unpack(carry[1], carry[2])
            done, _ = self._ended(state)
            return ~done & (state.iterations < limit)

        def body(carry):
            y, state, aux = self._update(fn, carry[0], args, options,
                                         layout.unpack(carry[1], carry[2]))
            return (y, *layout.pack(state), aux)

        y, rest, packed, aux = jax.lax.while_loop(cond, body, (y, *layout.pack(state), aux))
        return y, layout.unpack(rest, packed), aux

    def _restarted(self, fn, start, args, options, carry):
        """`carry = (y, state, aux)` moved to the point `start`, with fresh bookkeeping."""
        y, state, aux = carry
        dtype = ravel_pytree(y)[0].dtype
        _, unravel = ravel_pytree(y)
        point = unravel(ravel_pytree(start)[0].astype(dtype))
        f, _ = fn(point, args)
        inf = jnp.full((), jnp.inf, dtype)
        no = jnp.array(False)
        zero = jnp.zeros_like(state.stalls)
        fresh = NewtonState(ravel_pytree(f)[0], inf, no, no, zero, state.iterations,
                            jnp.array(True))
        return point, fresh, aux

    def _update(self, fn, y, args, options, state):
        """One Newton update from `y` (with backtracking far from the root)."""
        flat_y, unravel = ravel_pytree(y)
        dtype = flat_y.dtype
        scale = jnp.asarray(hints_of(options).scale, dtype)

        def residual(v):
            out, aux = fn(unravel(v), args)
            return ravel_pytree(out)[0], aux

        d = self._direction(fn, y, args, options, state.f)
        fmax = jnp.max(jnp.abs(state.f))
        near = fmax <= self._tolerance("floor", dtype) * scale
        f_full, aux_full = residual(flat_y + d)

        def enough(f_try, a):
            return near | (jnp.max(jnp.abs(f_try)) <= (1 - 1e-4 * a) * fmax)

        def cond(carry):
            a, f_try, _, k = carry
            return ~enough(f_try, a) & (k < self.max_backtracks)

        def body(carry):
            a, _, _, k = carry
            a = a / 2
            f_try, aux = residual(flat_y + a * d)
            return a, f_try, aux, k + 1

        one = jnp.ones((), dtype)
        a, f_new, aux, _ = jax.lax.while_loop(cond, body, (one, f_full, aux_full, 0))
        decreased = enough(f_new, a)
        new = jnp.where(decreased, flat_y + a * d, flat_y)
        f_new = jnp.where(decreased, f_new, state.f)
        fmax_new = jnp.max(jnp.abs(f_new))
        norm = jnp.max(jnp.abs(a * d))
        iterations = state.iterations + 1
        converged = fmax_new <= self._tolerance("ftol", dtype) * scale
        if self.confirm:
            converged = converged & self._confirmed(norm, new, dtype)
        # Rounding has taken over once a full update near the root is no smaller than the
        # one before it.
        at_floor = near & (norm >= state.step_norm) & (
            fmax_new <= self._tolerance("floor", dtype) * scale
        )
        stalls = jnp.where(decreased, 0, state.stalls + 1)
        step_norm = jnp.where(decreased, norm, state.step_norm)
        state = NewtonState(f_new, step_norm, converged, at_floor, stalls, iterations,
                            state.restarted)
        return unravel(new), state, aux

    def _direction(self, fn, y, args, options, f: Array) -> Array:
        """Newton's update `−J⁻¹ F` at `y`: with the hint `inverse` where the caller gives
        one (the formulation's own inverse, cheaper than LAPACK at the sizes of a step; with
        `pivoted_fallback`, by LU where it is not finite), else by LU of the Jacobian."""
        dtype = f.dtype
        jac = self._jacobian(fn, y, args, options)

        def by_lu():
            return solve(jac.astype(dtype), -f)

        given = hints_of(options).inverse
        if given is None:
            return by_lu()
        inverse = given(jac, y, args)
        d = -(inverse @ f.astype(inverse.dtype)).astype(dtype)
        if not self.pivoted_fallback:
            return d
        # a non-finite inverse makes the update non-finite: testing the update is cheaper
        return unless_all_skip(~jnp.all(jnp.isfinite(d)), by_lu, d)

    def _ended(self, state: NewtonState):
        """Whether the solve has ended at `state`, and how."""
        fmax = jnp.max(jnp.abs(state.f))
        nonfinite = ~jnp.isfinite(fmax)
        stalled = state.stalls >= self.max_stalls
        result = optx.RESULTS.where(
            nonfinite,
            optx.RESULTS.nonfinite,
            optx.RESULTS.where(stalled, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful),
        )
        return state.converged | state.at_floor | nonfinite | stalled, result

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, tags
        done, result = self._ended(state)
        if hints_of(options).max_iterations is None:
            return done, result
        # The whole solve ran in the first step (`_whole_solve`); a start that has already
        # ended (a non-finite residual) is not stepped at all.
        ran = (state.iterations > 0) | done
        result = optx.RESULTS.where(
            done, result, optx.RESULTS.nonlinear_max_steps_reached
        )
        return ran, optx.RESULTS.where(ran, result, optx.RESULTS.successful)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}
