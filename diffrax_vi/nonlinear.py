"""Root finders for the per-step variational equations.

The equations of a network step are square but rank-deficient by construction (redundant
neurons, zero output weights, the rescaling symmetry of ReLUᵏ), so a plain LU Newton step is
undefined exactly where the solution lives. Two damped Newton methods handle this:

* `RegularisedNewton`: `d = −(J + λI)⁻¹ F`, the reference's `regularization_factor` (λ is added
  to the raw diagonal, so the pairing of equations and unknowns matters);
* `LevenbergMarquardt`: `d = −(JᵀJ + μI)⁻¹ JᵀF` with `μ = λ·‖F‖`, which converges
  quadratically to non-isolated roots (Yamashita–Fukushima) and always gives a descent
  direction for `½‖F‖²`.

Both take an Armijo backtracking line search on `½‖F‖²`, form the Jacobian densely with
`jax.jacfwd`, and are `optimistix.AbstractRootFinder`s, so `optimistix.root_find` supplies
implicit differentiation of the converged step. Tolerances left as `None` are set from the
machine epsilon of the unknowns' dtype. Any optimistix root finder (`optx.Newton`,
`optx.Dogleg`, `optx.LevenbergMarquardt`, ...) may be used in their place.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

__all__ = ["AbstractDampedNewton", "RegularisedNewton", "LevenbergMarquardt", "default_tolerances"]


def default_tolerances(dtype) -> dict[str, float]:
    """Tolerances used when a root finder leaves them as `None`, scaled by `eps(dtype)`.

    Residuals are compared with `tol·scale`, where `scale` comes from the caller through
    `options["scale"]` (default 1; `NetworkVI` passes `1 + max(|q_n|, |p_n|)`).

    - `ftol = 64·eps`: converged when `max|F| ≤ ftol·scale`;
    - `floor = eps^(3/4)`: also converged when the residual has stopped decreasing (it failed
      to halve `patience_floor` iterations in a row) while below `floor·scale`: it sits at its
      round-off floor, which for a network step lies well above `eps`.
    """
    eps = float(jnp.finfo(dtype).eps)
    return dict(ftol=64 * eps, floor=eps**0.75)


class _DampedNewtonState(eqx.Module):
    f: Array  # flat residual at the current iterate
    fbest: Array  # smallest max|F| met so far
    idle: Array  # iterations since max|F| last fell below half of fbest
    result: optx.RESULTS
    stalls: Array  # consecutive failed line searches


class AbstractDampedNewton(optx.AbstractRootFinder):
    """Damped Newton with a dense Jacobian and Armijo backtracking on `½‖F‖²`.

    Subclasses choose the step from the Jacobian `J` and residual `F`.
    """

    lam: float
    ftol: float | None
    floor: float | None
    max_backtracks: int
    max_stalls: int
    patience_floor: int
    patience: int

    def direction(self, jac: Array, f: Array) -> Array:
        raise NotImplementedError

    def _tols(self, dtype):
        tol = default_tolerances(dtype)
        for name in ("ftol", "floor"):
            if getattr(self, name) is not None:
                tol[name] = getattr(self, name)
        return tol

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del options, aux_struct, tags
        f, _ = fn(y, args)
        flat_f, _ = ravel_pytree(f)
        flat_y, _ = ravel_pytree(y)
        return _DampedNewtonState(
            f=flat_f,
            fbest=jnp.full((), jnp.inf, flat_f.dtype),
            idle=jnp.array(0, jnp.int32),
            result=optx.RESULTS.successful,
            stalls=jnp.array(0, jnp.int32),
        )

    def step(self, fn, y, args, options, state, tags):
        del options, tags
        flat_y, unravel = ravel_pytree(y)
        dtype = flat_y.dtype

        def residual(v):
            out, aux = fn(unravel(v), args)
            return ravel_pytree(out)[0], aux

        def residual_with_copy(v):
            f, aux = residual(v)
            return f, (f, aux)

        jac, (f, aux) = jax.jacfwd(residual_with_copy, has_aux=True)(flat_y)
        d = self.direction(jac, f)
        slope = jnp.dot(f, jac @ d)  # derivative of ½‖F(y + a d)‖² at a = 0
        phi0 = 0.5 * jnp.dot(f, f)
        eps = jnp.finfo(dtype).eps
        c1 = jnp.asarray(1e-4, dtype)
        allowance = 4 * eps * phi0

        def trial(a):
            fa, _ = residual(flat_y + a * d)
            phi = 0.5 * jnp.dot(fa, fa)
            return fa, jnp.where(jnp.isfinite(phi), phi, jnp.inf)

        def accept(a, phi):
            return phi <= phi0 + c1 * a * jnp.minimum(slope, 0) + allowance

        def cond(carry):
            i, a, _, phi, _, _ = carry
            return (i < self.max_backtracks) & ~accept(a, phi)

        def body(carry):
            i, a, best_a, best_phi, _, _ = carry
            a = 0.5 * a
            fa, phi = trial(a)
            better = phi < best_phi
            return (
                i + 1,
                a,
                jnp.where(better, a, best_a),
                jnp.where(better, phi, best_phi),
                fa,
                phi,
            )

        one = jnp.ones((), dtype)
        f1, phi1 = trial(one)
        init = (jnp.array(0, jnp.int32), one, one, phi1, f1, phi1)
        _, a, best_a, best_phi, fa, phi = jax.lax.while_loop(cond, body, init)
        ok = accept(a, phi)
        # No acceptable point: fall back to the best trial seen (a stall).
        a_used = jnp.where(ok, a, best_a)
        f_used = jax.lax.cond(ok, lambda: fa, lambda: trial(best_a)[0])
        stalled = ~ok
        stalls = jnp.where(stalled, state.stalls + 1, 0)
        new_y = flat_y + a_used * d
        fmax = jnp.max(jnp.abs(f_used))
        progress = fmax < 0.5 * state.fbest
        idle = jnp.where(progress, 0, state.idle + 1)
        finite = jnp.all(jnp.isfinite(d)) & jnp.isfinite(best_phi)
        gave_up = (stalls > self.max_stalls) | (idle >= self.patience)
        result = optx.RESULTS.where(
            finite,
            optx.RESULTS.where(gave_up, optx.RESULTS.nonlinear_divergence, state.result),
            optx.RESULTS.nonfinite,
        )
        new_state = _DampedNewtonState(
            f=f_used,
            fbest=jnp.where(progress, fmax, state.fbest),
            idle=idle,
            result=result,
            stalls=stalls,
        )
        return unravel(new_y), new_state, aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, args, tags
        dtype = state.f.dtype
        tol = self._tols(dtype)
        scale = jnp.asarray(options.get("scale", 1.0), dtype)
        fmax = jnp.max(jnp.abs(state.f))
        at_floor = (state.idle >= self.patience_floor) & (fmax <= tol["floor"] * scale)
        converged = (fmax <= tol["ftol"] * scale) | at_floor
        failed = state.result != optx.RESULTS.successful
        return converged | failed, state.result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


class RegularisedNewton(AbstractDampedNewton):
    """Newton's method with a diagonal shift, `d = −(J + λI)⁻¹ F`, and Armijo backtracking.

    This is the reference's `Newton()` with `regularization_factor = λ`: the shift does not
    change the roots, it keeps the linear solve defined where `J` is singular (at the price of
    linear convergence along near-null directions).

    **Arguments:**

    - `lam`: the shift λ.
    - `ftol`, `floor`: residual tolerances (`None`: from `default_tolerances`).
    - `max_backtracks`: halvings of the step in the line search.
    - `max_stalls`: consecutive failed line searches before giving up.
    - `patience_floor`: iterations without progress that mark the round-off floor.
    - `patience`: iterations without progress (residual halving) before giving up.
    """

    lam: float = 1e-8
    ftol: float | None = None
    floor: float | None = None
    max_backtracks: int = eqx.field(static=True, default=30)
    max_stalls: int = eqx.field(static=True, default=3)
    patience_floor: int = eqx.field(static=True, default=3)
    patience: int = eqx.field(static=True, default=25)
    rtol: float | None = None  # unused; diffrax reads it off any implicit solver's root finder
    atol: float | None = None  # unused; as rtol
    norm: Callable = optx.max_norm

    def direction(self, jac, f):
        n = f.shape[0]
        lam = jnp.asarray(self.lam, f.dtype)
        return -jnp.linalg.solve(jac + lam * jnp.eye(n, dtype=f.dtype), f)


class LevenbergMarquardt(AbstractDampedNewton):
    """Levenberg–Marquardt, `d = −(JᵀJ + μI)⁻¹ JᵀF` with `μ = λ‖F‖₂`, and Armijo backtracking.

    The damping vanishes as the residual does, so convergence is quadratic also when the roots
    form a manifold (singular `J` at the solution), and the step is always a descent direction.

    **Arguments:** as `RegularisedNewton`; `lam` scales the damping `μ = λ‖F‖`.
    """

    lam: float = 1e-3
    ftol: float | None = None
    floor: float | None = None
    max_backtracks: int = eqx.field(static=True, default=30)
    max_stalls: int = eqx.field(static=True, default=3)
    patience_floor: int = eqx.field(static=True, default=3)
    patience: int = eqx.field(static=True, default=25)
    rtol: float | None = None  # unused; diffrax reads it off any implicit solver's root finder
    atol: float | None = None  # unused; as rtol
    norm: Callable = optx.max_norm

    def direction(self, jac, f):
        n = f.shape[0]
        eps = jnp.finfo(f.dtype).eps
        mu = jnp.asarray(self.lam, f.dtype) * jnp.sqrt(jnp.dot(f, f))
        mu = jnp.maximum(mu, (eps * jnp.max(jnp.abs(jac))) ** 2)
        # Least squares on [J; √μ I] d ≈ [−F; 0] by QR: no normal equations, so nothing is
        # squared and a tiny μ next to a singular J stays well defined.
        augmented = jnp.concatenate([jac, jnp.sqrt(mu) * jnp.eye(n, dtype=f.dtype)], axis=0)
        rhs = jnp.concatenate([-f, jnp.zeros_like(f)])
        qmat, rmat = jnp.linalg.qr(augmented)
        return jax.scipy.linalg.solve_triangular(rmat, qmat.T @ rhs)
