"""Root finders for the per-step variational equations.

The equations of a network step are square but rank-deficient by construction (redundant
neurons, zero output weights, the rescaling symmetry of ReLUᵏ, nearly collinear neurons), so a
plain LU Newton step is undefined exactly where the solution lives. Two damped Newton methods
handle this:

* `LevenbergMarquardt`: `d = −(JᵀJ + μI)⁻¹ JᵀF` with `μ = λ‖F‖`, which converges fast to roots
  that form a manifold (singular `J` at the solution) and always gives a descent direction;
* `RegularisedNewton`: `d = −(J + λI)⁻¹ F`, the reference's `regularization_factor` (λ is
  added to the raw diagonal, so the pairing of equations and unknowns matters).

Both take an Armijo backtracking line search on `½‖F‖²`, reuse the last Jacobian while it
keeps cutting the residual (`reuse_jacobian`), form the Jacobian densely (by
default with `jax.jacfwd`; `jacobian="rev"` uses `jax.jacrev`; `"auto"` and `"structured"` take
the matrix the caller assembles, which `NetworkVI` does in closed form for shallow networks;
each changes the rounding and with it the iteration path), and are
`optimistix.AbstractRootFinder`s, so `optimistix.root_find` supplies implicit differentiation
of a converged step. Another optimistix root finder can be passed in their place, but it has
neither the convergence tests below nor the second start, and a plain Newton iteration may
stop as singular on the rank-deficient systems of a network step.

**When is a step converged?** Tolerances left as `None` scale with the machine epsilon of the
unknowns' dtype (`default_tolerances`). Because the Jacobian is numerically rank-deficient, part
of the residual lies in directions the iteration cannot reduce and that do not move the step's
result. So besides a residual at `ftol`, a step also counts as converged when the residual has
stopped falling, is below `floor`, and the caller's outputs of interest (passed as the callable
the hint `outputs`; `NetworkVI` passes `y ↦ (q_{n+1}, p_{n+1})`) no longer change beyond a
few ulps. A residual that stops falling anywhere else is a failure.

**How a solve fails.** `optimistix.RESULTS.nonlinear_max_steps_reached` (iteration cap),
`nonlinear_divergence` (the residual stopped falling, or the line search failed `max_stalls`
times in a row, above the tolerance), `nonfinite` (NaN/inf in the residual, or everywhere along
the step) and `singular` (finite residual but a non-finite Newton direction: the linear solve
broke down). `NetworkVI` turns them into the step failures of `diffrax_vi._results`.

**A second start.** A caller may pass the hint `fallback`, a function of `args` returning
another starting point (and optionally the hint `fallback_usable`, a function of `args`
returning whether to use it). Where an iteration would end the solve with a failure, the solve
restarts from that point once, with fresh bookkeeping and the same iteration cap; the final
state's `restarted` says whether it did. The hint `start_at_fallback`, a function of `args`
returning a boolean, makes the solve begin at the fallback instead of `y` (which then only
gives the shape), with no restart after it. `NetworkVI` passes a fresh trajectory fit as the
fallback when its seed may come from the previous step, and starts there when the carried
seed is unusable: the fit then exists once in the compiled step, evaluated only where needed.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from .._lazy import unless_all_skip
from .._linalg import damped_least_squares, solve
from .step_hints import AbstractStepRootFinder, hints_of

__all__ = ["AbstractDampedNewton", "RegularisedNewton", "LevenbergMarquardt", "default_tolerances"]


def default_tolerances(dtype) -> dict[str, float]:
    """Tolerances used when a root finder leaves them as `None`, scaled by `eps(dtype)`.

    Residuals are compared with `tol·scale`, where `scale` comes from the caller through
    the hint `scale` (default 1; `NetworkVI` passes `1 + max(|q_n|, |p_n|)`).

    - `ftol = min(64·eps, eps^(3/4))`: converged when `max|F| ≤ ftol·scale`;
    - `floor = sqrt(eps)`: also converged when the residual is below `floor·scale`, did not
      halve for `settle` iterations (default 3), and the last iteration was exact (fresh
      Jacobian) and changed the outputs by at most `otol·(1 + |output|)` (`otol = 64·eps`),
      or by at most
      `otol_slow = eps^(3/4)` after `patience_floor` iterations without the residual halving,
      or found no decrease;
    - `floor_moving = eps^(5/8)`: also converged when the residual is below `floor_moving·scale`
      and did not halve for `patience_floor` iterations although the outputs still move: the
      iterate then slides along a manifold of near-roots whose outputs differ by less than the
      equations can resolve;
    - without the hint `outputs`: converged when the residual did not halve for
      `patience_floor` iterations while below `eps^(3/4)·scale`.

    The output test is what ends most steps: the rank-deficient Jacobian leaves a residual
    floor near `eps·‖J‖·‖x‖`, usually above `ftol`, where results move with the iteration
    path. Ending sooner (a smaller `settle`, a larger `otol`) saves iterations and lets the
    result move more at that level; a very loose `otol` lets iterates that creep along
    near-roots end far from a root.
    """
    eps = float(jnp.finfo(dtype).eps)
    return dict(
        ftol=min(64 * eps, eps**0.75), floor=eps**0.5, floor_moving=eps**0.625, otol=64 * eps,
        otol_slow=eps**0.75, floor_no_outputs=eps**0.75,
    )


class _DampedNewtonState(eqx.Module):
    f: Array  # flat residual at the current iterate
    out: Array  # flat outputs of interest at the current iterate
    out_change: Array  # max |Δ outputs| / (1 + |outputs|) over the last iteration
    fbest: Array  # smallest max|F| met so far
    idle: Array  # iterations since max|F| last fell below half of fbest
    result: optx.RESULTS
    stalls: Array  # consecutive failed line searches
    jac: Array  # the Jacobian the last direction was computed with
    refresh: Array  # whether the next iteration evaluates a fresh Jacobian
    reused: Array  # iterations since the Jacobian was last evaluated
    exact: Array  # whether the last iteration used a Jacobian evaluated at its iterate
    f0: Array  # max|F| at the starting point (for `convergence="reference"`)
    still: Array  # whether the last iteration changed x or F by at most 2 eps (relative)
    restarted: Array  # whether the solve has restarted from the hint `fallback` after a failure
    pending: Array  # whether the next iteration starts at the fallback (`start_at_fallback`)
    from_fallback: Array  # whether the solve is running from the fallback (no further restart)


def _start_state(
    f: Array, out: Array, jac: Array, restarted, pending=False, from_fallback=False
) -> _DampedNewtonState:
    """The state at a starting point (the seed, or the fallback of a restart): fresh
    bookkeeping, a Jacobian due on the first iteration."""
    dtype = f.dtype
    return _DampedNewtonState(
        f=f,
        out=out,
        out_change=jnp.full((), jnp.inf, dtype),
        fbest=jnp.full((), jnp.inf, dtype),
        idle=jnp.array(0, jnp.int32),
        result=optx.RESULTS.successful,
        stalls=jnp.array(0, jnp.int32),
        jac=jac,
        refresh=jnp.array(True),
        reused=jnp.array(0, jnp.int32),
        exact=jnp.array(False),
        f0=jnp.max(jnp.abs(f), initial=0.0),
        still=jnp.array(False),
        restarted=jnp.asarray(restarted),
        pending=jnp.asarray(pending),
        from_fallback=jnp.asarray(from_fallback),
    )


def _flat_outputs(options, y, dtype) -> Array:
    outputs = hints_of(options).outputs
    if outputs is None:
        return jnp.zeros((0,), dtype)
    return ravel_pytree(outputs(y))[0].astype(dtype)


class AbstractDampedNewton(AbstractStepRootFinder):
    """Damped Newton with a dense Jacobian and Armijo backtracking on `½‖F‖²`.

    Subclasses choose the step from the Jacobian `J` and residual `F` (`direction`).
    """

    hints_read: ClassVar[frozenset[str]] = frozenset(
        {"scale", "outputs", "jacobian", "fallback", "fallback_usable", "start_at_fallback"}
    )

    lam: eqx.AbstractVar[float]
    ftol: float | None = None
    floor: float | None = None
    otol: float | None = None
    max_backtracks: int = eqx.field(static=True, default=30)
    max_stalls: int = eqx.field(static=True, default=3)
    patience_floor: int = eqx.field(static=True, default=10)
    settle: int = eqx.field(static=True, default=3)
    patience: int = eqx.field(static=True, default=50)
    rtol: float | None = None
    atol: float | None = None
    norm: Callable = optx.max_norm
    jacobian: str = eqx.field(static=True, default="fwd")
    reuse_jacobian: int = eqx.field(static=True, default=0)
    convergence: str = eqx.field(static=True, default="strict")

    def __check_init__(self):
        if self.jacobian not in ("auto", "rev", "fwd", "structured"):
            raise ValueError(
                f"jacobian must be 'auto', 'fwd', 'rev' or 'structured', got {self.jacobian!r}"
            )
        if self.convergence not in ("strict", "reference"):
            raise ValueError(
                f"convergence must be 'strict' or 'reference', got {self.convergence!r}"
            )
        for name in ("reuse_jacobian", "settle"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"{name} must be a non-negative integer, got {value!r}")

    def direction(self, jac: Array, f: Array, stalls: Array | int = 0) -> Array:
        """The step from the Jacobian and the residual; `stalls` counts the failed line
        searches just before (a subclass may damp the step harder after them)."""
        raise NotImplementedError

    def _reference_mode(self):
        """Whether to stop the reference's way (`convergence`); a subclass may return a
        traced boolean so that one compiled program serves both tests."""
        return self.convergence == "reference"

    def was_restarted(self, state: _DampedNewtonState) -> Array:
        return state.restarted

    def final_residual(self, state: _DampedNewtonState, dtype) -> tuple[Array, float]:
        return state.f, self.tolerances(dtype)["ftol"]

    def jacobian_mode(self) -> str:
        return self.jacobian

    def tolerances(self, dtype) -> dict[str, float]:
        """`ftol`, `floor` and `otol` in effect for `dtype`: the given ones, else the defaults
        (`default_tolerances`)."""
        tol = default_tolerances(dtype)
        for name in ("ftol", "floor", "otol"):
            if getattr(self, name) is not None:
                tol[name] = getattr(self, name)
        return tol

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del aux_struct, tags
        f, _ = fn(y, args)
        flat_f, _ = ravel_pytree(f)
        dtype = flat_f.dtype
        jac = jnp.zeros((flat_f.size, ravel_pytree(y)[0].size), dtype)
        start_at_fallback = hints_of(options).start_at_fallback
        pending = (
            jnp.array(False)
            if start_at_fallback is None or hints_of(options).fallback is None
            else jnp.asarray(start_at_fallback(args))
        )
        return _start_state(
            flat_f, _flat_outputs(options, y, dtype), jac, restarted=False, pending=pending
        )

    def step(self, fn, y, args, options, state, tags):
        del tags
        flat_y, unravel = ravel_pytree(y)
        dtype = flat_y.dtype

        def residual(v):
            out, aux = fn(unravel(v), args)
            return ravel_pytree(out)[0], aux

        if hints_of(options).fallback is not None:
            y, state = self._switch_to_fallback(residual, args, options, y, state)
            flat_y = ravel_pytree(y)[0]
        jac, f, aux, refresh = self._jacobian_here(residual, y, flat_y, args, options, state)
        reused = jnp.where(refresh, 0, state.reused + 1)
        d = self.direction(jac, f, state.stalls)
        ok, a, best_a, best_phi, best_f, fa, phi0 = self._line_search(residual, flat_y, f, jac, d)
        # No acceptable point: take the best trial seen, and count a stall. With a reused
        # Jacobian that is not a stall yet: the next iteration retries with a fresh one, and
        # stays put unless the best trial decreased the residual.
        a_used = jnp.where(ok, a, best_a)
        stalls = jnp.where(ok | ~refresh, 0, state.stalls + 1)
        a_used = jnp.where(ok | refresh | (best_phi < phi0), a_used, 0)
        f_used = jnp.where(ok, fa, jnp.where(a_used != 0, best_f, f))
        # A finite residual with a non-finite direction is a broken-down linear solve
        # (`singular`); a non-finite residual, or one that turns non-finite all along the
        # direction, is `nonfinite`. Either way the iterate stays at the last finite point,
        # so the state reports the residual there.
        f_finite = jnp.all(jnp.isfinite(f))
        d_finite = jnp.all(jnp.isfinite(d))
        good = f_finite & d_finite & jnp.isfinite(best_phi)
        new_flat_y = jnp.where(good, flat_y + a_used * d, flat_y)
        f_used = jnp.where(good, f_used, f)
        new_y = unravel(new_flat_y)
        still = self._still(flat_y, new_flat_y, f, f_used)
        out = _flat_outputs(options, new_y, dtype)
        out_change = jnp.max(jnp.abs(out - state.out) / (1 + jnp.abs(out)), initial=0.0)
        fmax = jnp.max(jnp.abs(f_used))
        progress = fmax < 0.5 * state.fbest
        idle = jnp.where(progress, 0, state.idle + 1)
        result = optx.RESULTS.where(good, state.result, optx.RESULTS.nonfinite)
        result = optx.RESULTS.where(f_finite & ~d_finite, optx.RESULTS.singular, result)
        new_state = _DampedNewtonState(
            f=f_used,
            out=out,
            out_change=out_change.astype(dtype),
            fbest=jnp.where(progress, fmax, state.fbest),
            idle=idle,
            result=result,
            stalls=stalls,
            jac=jac,
            # Keep the Jacobian while its full step is accepted and cuts the residual 4-fold,
            # for at most `reuse_jacobian` iterations in a row, and not at the residual floor,
            # where only exact iterations can show convergence.
            reused=reused,
            exact=refresh,
            f0=state.f0,
            still=still,
            refresh=~(ok & (a == 1) & (fmax < 0.25 * jnp.max(jnp.abs(f))))
            | (reused >= self.reuse_jacobian)
            | (fmax <= self.tolerances(dtype)["floor"]
               * jnp.asarray(hints_of(options).scale, dtype)),
            restarted=state.restarted,
            pending=state.pending,
            from_fallback=state.from_fallback,
        )
        return new_y, new_state, aux

    def _jacobian_here(self, residual, y, flat_y, args, options, state):
        """`(J, F, aux, fresh)` at the iterate: a fresh Jacobian (by `jacobian`'s rule), or
        with `reuse_jacobian` the state's where it is still due for reuse (`fresh` false)."""
        dtype = flat_y.dtype

        def residual_and_copy(v):
            f, aux = residual(v)
            return f, (f, aux)

        # The residual at the iterate is in the state already (the line search, `init` or the
        # switch to the fallback computed it there); without an `aux` output (the case of
        # `optx.root_find(..., has_aux=False)`) it is not evaluated again. Every copy of the
        # residual in the loop body is another piece of program for XLA to compile.
        no_aux = jax.eval_shape(lambda: residual(flat_y)[1]) is None

        def residual_here():
            if no_aux:
                return state.f, None
            return residual(flat_y)

        given = hints_of(options).jacobian
        if self.jacobian == "structured" and given is None:
            raise ValueError(
                "jacobian='structured' needs the caller to pass the Jacobian as "
                "the jacobian of its StepHints (a function of the unknowns and args); NetworkVI "
                "does so "
                "for a ShallowNetBasis with free endpoints"
            )
        if given is not None and self.jacobian in ("auto", "structured"):

            def fresh():
                f, aux = residual_here()
                return given(y, args).astype(dtype), f, aux
        else:
            jacobian = jax.jacrev if self.jacobian == "rev" else jax.jacfwd

            def fresh():
                jac, (f, aux) = jacobian(residual_and_copy, has_aux=True)(flat_y)
                return jac, f, aux

        if self.reuse_jacobian > 0:
            # The residual at the iterate is already in the state; evaluate `aux` alongside.
            # Lazy under vmap: an ensemble pays for the Jacobian only when a member needs it.
            _, aux = residual_here()
            refresh = state.refresh
            jac, f, aux = unless_all_skip(refresh, fresh, (state.jac, state.f, aux))
        else:
            refresh = jnp.array(True)
            jac, f, aux = fresh()
        return jac, f, aux, refresh

    def _line_search(self, residual, flat_y, f, jac, d):
        """Armijo backtracking on `½‖F‖²` along `d` from the full step: whether a trial was
        acceptable, its step `a`, the best trial's step, `½‖F‖²` and residual, the last
        trial's residual, and `½‖F‖²` at the start."""
        dtype = flat_y.dtype
        slope = jnp.dot(f, jac @ d)  # derivative of ½‖F(y + a d)‖² at a = 0
        phi0 = 0.5 * jnp.dot(f, f)
        c1 = jnp.asarray(1e-4, dtype)
        allowance = 4 * jnp.finfo(dtype).eps * phi0

        def trial(a):
            fa, _ = residual(flat_y + a * d)
            phi = 0.5 * jnp.dot(fa, fa)
            return fa, jnp.where(jnp.isfinite(phi), phi, jnp.asarray(jnp.inf, dtype))

        def acceptable(a, phi):
            return phi <= phi0 + c1 * a * jnp.minimum(slope, 0) + allowance

        # Backtracking from the full step: trial `i` is at `a = 2^-i`, `i = 0 … max_backtracks`,
        # until one is acceptable. One call site of the residual; the residuals of the last
        # and of the best trial are carried along, not evaluated again.
        def cond(carry):
            i, a, _, _, _, _, phi = carry
            return (i == 0) | ((i <= self.max_backtracks) & ~acceptable(a, phi))

        def body(carry):
            i, a, best_a, best_phi, best_f, _, _ = carry
            a = jnp.where(i == 0, a, 0.5 * a)
            fa, phi = trial(a)
            better = (phi < best_phi) | (i == 0)
            best_a = jnp.where(better, a, best_a)
            best_phi = jnp.where(better, phi, best_phi)
            best_f = jnp.where(better, fa, best_f)
            return i + 1, a, best_a, best_phi, best_f, fa, phi

        one = jnp.ones((), dtype)
        inf = jnp.full((), jnp.inf, dtype)
        carry = (jnp.array(0, jnp.int32), one, one, inf, f, f, inf)
        _, a, best_a, best_phi, best_f, fa, phi = jax.lax.while_loop(cond, body, carry)
        return acceptable(a, phi), a, best_a, best_phi, best_f, fa, phi0

    def _still(self, flat_y, new_flat_y, f, f_used) -> Array:
        """Whether the iteration changed `x` or `F` by at most `2 eps` (relative): what the
        reference's test reads (`convergence="reference"`), else always false."""
        if self._reference_mode() is False:
            return jnp.array(False)
        eps = jnp.finfo(flat_y.dtype).eps
        return (jnp.max(jnp.abs(new_flat_y - flat_y), initial=0.0)
                <= 2 * eps * jnp.max(jnp.abs(new_flat_y), initial=0.0)) | (
            jnp.max(jnp.abs(f_used - f), initial=0.0)
            <= 2 * eps * jnp.max(jnp.abs(f_used), initial=0.0))

    def _restartable(self, args, options, state, result=None) -> Array:
        """Whether the solve has failed and may restart from the caller's fallback (`result`:
        the outcome's result, where the caller has it already)."""
        if hints_of(options).fallback is None:
            return jnp.array(False)
        if result is None:
            _, result = self._outcome(options, state)
        usable = hints_of(options).fallback_usable
        usable = jnp.array(True) if usable is None else usable(args)
        return (result != optx.RESULTS.successful) & ~state.from_fallback & usable

    def _switch_to_fallback(self, residual, args, options, y, state):
        """Before an iteration: where the solve is due to start at the caller's fallback point
        (the hint `fallback(args)`), or failed and may restart there once, continue from
        that point with fresh bookkeeping; the iteration cap is shared. The one evaluation of
        the fallback in the compiled loop runs only where some member of a batch needs it."""
        switch = state.pending | self._restartable(args, options, state)

        def fresh_start():
            start = jax.lax.stop_gradient(hints_of(options).fallback(args))
            f, _ = residual(ravel_pytree(start)[0])
            return start, f

        start, f = unless_all_skip(switch, fresh_start, (y, state.f))
        out = _flat_outputs(options, start, state.f.dtype)
        restart = _start_state(
            f, out, state.jac, restarted=~state.pending, from_fallback=True
        )
        pick = lambda a, b: jnp.where(switch, a, b)  # noqa: E731
        y = jax.tree_util.tree_map(pick, start, y)
        state = jax.tree_util.tree_map(pick, restart, state)
        return y, state

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, tags
        done, result = self._outcome(options, state)
        # Not done, and no failure yet, while a start at, or a restart from, the caller's
        # fallback is due (optimistix's loop stops at the first non-successful result).
        due = state.pending | self._restartable(args, options, state, result)
        return done & ~due, optx.RESULTS.where(due, optx.RESULTS.successful, result)

    def _outcome(self, options, state):
        """Whether the solve has converged or failed, and its result so far."""
        dtype = state.f.dtype
        tol = self.tolerances(dtype)
        scale = jnp.asarray(hints_of(options).scale, dtype)
        fmax = jnp.max(jnp.abs(state.f))
        stuck = state.idle >= self.patience_floor
        if hints_of(options).outputs is None:
            at_floor = (stuck | (state.stalls > 0)) & (fmax <= tol["floor_no_outputs"] * scale)
        else:
            settled = (state.out_change <= tol["otol"]) & (state.idle >= self.settle)
            creeping = stuck & (state.out_change <= tol["otol_slow"])
            no_descent = state.stalls > 0  # the line search found no decrease at all
            small = fmax <= tol["floor"] * scale
            at_floor = ((settled | creeping | no_descent) & small) | (
                stuck & (fmax <= tol["floor_moving"] * scale)
            )
        # A reused Jacobian converges slowly, so a small change of the outputs says nothing
        # after its iterations: the floor tests trust only an exact Newton iteration.
        converged = (fmax <= tol["ftol"] * scale) | (at_floor & state.exact)
        stalled = (state.stalls > self.max_stalls) | (state.idle >= self.patience)
        gave_up = ~converged & stalled
        reference = self._reference_mode()
        if reference is not False:
            eps = jnp.finfo(dtype).eps
            # The reference's test; a stalled solve is returned as if converged.
            converged_ref = (fmax <= 8 * eps) | stalled | (
                state.still & (fmax <= 8 * eps + jnp.sqrt(eps) * state.f0)
            )
            converged = jnp.where(reference, converged_ref, converged)
            gave_up = gave_up & ~jnp.asarray(reference)
        result = optx.RESULTS.where(gave_up, optx.RESULTS.nonlinear_divergence, state.result)
        failed = result != optx.RESULTS.successful
        return converged | failed, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


_COMMON_ARGS = """
    - `ftol`, `floor`: residual tolerances, `otol`: output-change tolerance (`None`: from
      `default_tolerances`).
    - `max_backtracks`: halvings of the step in the line search.
    - `max_stalls`: consecutive failed line searches before giving up.
    - `patience_floor`: iterations without the residual halving that mark its floor.
    - `settle`: iterations without the residual halving before settled outputs end the
      solve (default 3; fewer iterations per step, results that move at the floor level).
    - `patience`: iterations without the residual halving before giving up.
    - `jacobian`: `"fwd"` (default, `jax.jacfwd`), `"rev"` (`jax.jacrev`), `"structured"`
      (the caller's hint `jacobian`, required: a function of the unknowns and `args`
      returning the dense matrix) or `"auto"` (the caller's matrix where it passes one, else
      `jax.jacfwd`). `NetworkVI` assembles the matrix by coordinate blocks
      (`FreeEndpoints.jacobian`); under `"auto"` it passes it only where the blocks have a
      closed form (`ShallowNetBasis` without mirrored pairs, free endpoints), which is several
      times faster than `jax.jacfwd`. All give the same matrix up to rounding; the iteration path,
      and with it the result at the level of the residual floor, changes with it.
    - `reuse_jacobian`: keep the Jacobian of the previous iteration while its full step is
      accepted and cuts the residual at least four-fold, for at most this many iterations in
      a row (default 0: a fresh Jacobian on every iteration); a fresh one is evaluated
      otherwise, at the residual floor, and always before convergence is declared there.
      The Jacobian dominates an iteration's cost, so reuse saves time; it changes the
      iteration path, and with it the result at the level of the residual floor.
    - `convergence`: `"strict"` (default: the tests above) or `"reference"`, which mimics
      NonlinearIntegrators.jl (its SimpleSolvers defaults, in the max norm): converged when
      `max|F| ≤ 8 eps`, or when the last iteration changed `x` or `F` by at most `2 eps`
      relative and `max|F| ≤ 8 eps + sqrt(eps)·max|F(x₀)|`; and, as there, a solve that
      stalls (`max_stalls`, `patience`) returns its iterate as *successful*. Only the
      iteration cap, a non-finite residual and a broken-down linear solve still fail. This
      accepts points that are no roots at all: it exists to count convergence the way the
      reference's benchmark does, never for results.
    - `rtol`, `atol`, `norm`: unused; present because diffrax reads them off the root finder of
      any implicit solver.
"""


class LevenbergMarquardt(AbstractDampedNewton):
    """Levenberg–Marquardt, `d = −(JᵀJ + μI)⁻¹ JᵀF` with `μ = λ‖F‖₂`, and Armijo backtracking.

    The damping vanishes with the residual, so convergence stays fast when the roots form a
    manifold, and the step is always a descent direction for `½‖F‖²`. The step is computed by
    QR of `[J; √μ I]` (never the normal equations), which stays defined for a singular `J`.

    **Arguments:**

    - `lam`: scale λ of the damping `μ = λ‖F‖`. Default `1e-3`.
    - `stall_damping`: after `k` consecutive failed line searches (`k ≤ max_stalls`) the
      damping is `stall_damping^k·λ‖F‖`; it returns to `λ‖F‖` after an accepted step.
      Default `100`; `1` keeps the damping fixed (as before; see the changelog). Near a nearly
      singular Jacobian the small damping `λ‖F‖` gives a long step along near-null
      directions that no backtracking rescues, and the next iteration would try the same
      step again; the growing damping shortens it and turns it towards steepest descent.
    """

    lam: float = 1e-3
    stall_damping: float = 100.0

    def __check_init__(self):
        growth = self.stall_damping
        if isinstance(growth, bool) or not isinstance(growth, int | float) or not growth >= 1:
            raise ValueError(f"stall_damping must be a number >= 1, got {growth!r}")

    def direction(self, jac, f, stalls=0):
        eps = jnp.finfo(f.dtype).eps
        mu = jnp.asarray(self.lam, f.dtype) * jnp.sqrt(jnp.dot(f, f))
        # Damp harder after failed line searches (`stall_damping`), the growth computed in at
        # least float32 and capped so that float16 cannot overflow.
        wide = jnp.promote_types(f.dtype, jnp.float32)
        growth = jnp.asarray(self.stall_damping, wide) ** jnp.asarray(stalls, wide)
        mu = jnp.minimum(mu.astype(wide) * growth, jnp.finfo(f.dtype).max).astype(f.dtype)
        mu = jnp.maximum(mu, (eps * jnp.max(jnp.abs(jac))) ** 2)
        return damped_least_squares(jac, -f, jnp.sqrt(mu))


class RegularisedNewton(AbstractDampedNewton):
    """Newton's method with a diagonal shift, `d = −(J + λI)⁻¹ F`, and Armijo backtracking.

    This is the reference's `Newton()` with `regularization_factor = λ`: the shift does not
    change the roots, it keeps the linear solve defined where `J` is singular, at the price of
    slow convergence along near-null directions.

    **Arguments:**

    - `lam`: the shift λ. Default `2.4e-7` (`16·sqrt(eps)` of float64, the reference
      benchmark's value).
    """

    lam: float = 2.4e-7

    def direction(self, jac, f, stalls=0):
        del stalls
        n = f.shape[0]
        lam = jnp.asarray(self.lam, f.dtype)
        return -solve(jac + lam * jnp.eye(n, dtype=f.dtype), f)


LevenbergMarquardt.__doc__ += _COMMON_ARGS
RegularisedNewton.__doc__ += _COMMON_ARGS
