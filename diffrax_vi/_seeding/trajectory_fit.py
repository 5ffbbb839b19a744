"""`TrajectoryFit`: seed a nonlinear ansatz by a least-squares fit to the trajectory labels."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree

from .._linalg import damped_least_squares
from .._parameter_seed import AbstractParameterSeed, FitProblem
from .fit import frozen_values

__all__ = ["TrajectoryFit"]


class TrajectoryFit(AbstractParameterSeed):
    """Fit a nonlinear ansatz to the step's trajectory labels by Levenberg–Marquardt, from
    the previous step's converged parameters and from fixed initial parameters, and keep the
    better fit.

    `InitialWeights` hands the Newton solve either the previous step's weights or the fixed
    `init`, without looking at where the motion goes on the new step. For an ansatz whose
    parameters are only weakly pinned by one step (a cosine `W1 cos(W2 t + W3) + W4` on an arc
    much shorter than its period, where frequency, amplitude and offset nearly trade off), the
    converged weights wander between neighbouring branches from step to step, and neither
    start is then reliably inside the root's basin. This seed instead moves both starts onto
    the labels of the initial trajectory (e.g. `IntegratorExtrapolation`), minimising the
    Simpson-weighted misfit `Σ_i w_i ‖q_h(τ_i; θ) − y_i‖²` over `τ_i = i/N`, and returns the
    start whose fit is smaller (the previous step's on a tie, for continuity). With a
    modulated problem (interpolating endpoints) the model is `τ(1 − τ) q_h(τ; θ)`.

    Each fit is a fixed number of Levenberg–Marquardt iterations with Marquardt's scaling: the
    columns of the Jacobian are normalised before the damped least-squares step (solved by QR,
    never the normal equations), so the damping does not depend on the scale of a parameter
    (in absolute time the frequency's column is `t` times larger than the phase's); a step is
    taken only if it lowers the misfit, the damping shrinks after a success and grows after a
    failure. Everything is static in shape and runs in `lax` loops, so the seed jit-compiles
    with the solver, and the parameters may be any pytree of arrays (e.g. the tuple of
    per-coordinate weight vectors of `SymbolicAnsatz`), in the dtype of the targets.

    **Arguments:**

    - `init`: the fixed starting parameters, in the layout of the ansatz (for
      `SymbolicAnsatz`, one weight sequence per coordinate). The first step is fitted from
      them alone.
    - `restart_radius`: if given, the previous step's parameters are only used as a start
      while they lie within this Euclidean distance (over all parameters) of `init`, as in
      `InitialWeights`. Default `None`: always.
    - `iterations`: Levenberg–Marquardt iterations of each fit. Default 60.
    - `damping`: initial damping, relative to the scaled Jacobian (whose columns have unit
      norm). Default `1e-3`.
    """

    init: PyTree = eqx.field(static=True, converter=frozen_values)
    restart_radius: float | None = eqx.field(static=True, default=None)
    iterations: int = eqx.field(static=True, default=60)
    damping: float = eqx.field(static=True, default=1e-3)

    def __check_init__(self):
        if not isinstance(self.iterations, int) or self.iterations < 0:
            raise ValueError(f"iterations must be a non-negative integer, got {self.iterations!r}")
        if not self.damping > 0:
            raise ValueError(f"damping must be positive, got {self.damping!r}")
        if self.restart_radius is not None and not self.restart_radius >= 0:
            raise ValueError(
                f"restart_radius must be non-negative or None, got {self.restart_radius!r}"
            )

    def parameters(self, basis, problem: FitProblem):
        dtype = problem.targets.dtype
        init = basis.params_from(self.init, dtype)
        flat_init, unravel = ravel_pytree(init)
        flat_prev = ravel_pytree(problem.previous)[0].astype(dtype)
        if flat_prev.shape != flat_init.shape:
            raise ValueError(
                "the previous parameters and init have different sizes "
                f"({flat_prev.shape[0]} and {flat_init.shape[0]})"
            )

        use_prev = ~problem.fresh
        if self.restart_radius is not None:
            drift = jnp.sqrt(jnp.sum((flat_prev - flat_init) ** 2))
            use_prev = use_prev & (drift <= self.restart_radius)

        residual = _misfit(basis, problem, unravel, dtype)
        v_init, c_init = _levenberg_marquardt(residual, flat_init, self.iterations, self.damping)
        # The first step (or a restart) fits from init alone: the second fit is then skipped.
        v_prev, c_prev = jax.lax.cond(
            use_prev,
            lambda v: _levenberg_marquardt(residual, v, self.iterations, self.damping),
            lambda v: (v, jnp.asarray(jnp.inf, dtype)),
            flat_prev,
        )
        best = jnp.where(use_prev & (c_prev <= c_init), v_prev, v_init)
        return unravel(best)


def _misfit(basis, problem: FitProblem, unravel, dtype):
    """The weighted residual vector `√w_i (q_h(τ_i; θ) − y_i)` of a flat `θ`."""
    nodes = jnp.asarray(problem.nodes, dtype)
    sqrt_w = jnp.sqrt(jnp.asarray(problem.weights, dtype))[:, None]
    targets = problem.targets.astype(dtype)
    modulation = (
        None if problem.modulation is None else jnp.asarray(problem.modulation, dtype)[:, None]
    )

    def residual(v: Array) -> Array:
        theta = unravel(v)
        q = jax.vmap(lambda s: basis.evaluate(theta, s))(nodes)
        if modulation is not None:
            q = modulation * q
        return ((q - targets) * sqrt_w).ravel()

    return residual


def _cost(r: Array) -> Array:
    c = jnp.dot(r, r)
    return jnp.where(jnp.isfinite(c), c, jnp.asarray(jnp.inf, r.dtype))


def _levenberg_marquardt(residual, v0: Array, iterations: int, damping: float):
    """`iterations` scaled Levenberg–Marquardt steps on `‖residual(v)‖²` from `v0`; returns
    the final `v` and its cost (`inf` if never finite)."""
    dtype = v0.dtype
    tiny = jnp.finfo(dtype).tiny
    r0 = residual(v0)

    def body(_, carry):
        v, r, cost, mu = carry
        jac = jax.jacfwd(residual)(v)
        # Marquardt scaling: unit columns, so μ is relative and scale-free per parameter.
        norms = jnp.sqrt(jnp.sum(jac**2, axis=0))
        norms = jnp.where(norms > tiny, norms, jnp.ones_like(norms))
        step = damped_least_squares(jac / norms, -r, jnp.sqrt(mu)) / norms
        v_try = v + step
        r_try = residual(v_try)
        cost_try = _cost(r_try)
        better = (cost_try < cost) & jnp.all(jnp.isfinite(step))
        v = jnp.where(better, v_try, v)
        r = jnp.where(better, r_try, r)
        cost = jnp.where(better, cost_try, cost)
        mu = jnp.where(better, jnp.maximum(mu / 3, 1e-12), jnp.minimum(mu * 4, 1e12))
        return v, r, cost, mu.astype(dtype)

    carry = (v0, r0, _cost(r0), jnp.asarray(damping, dtype))
    v, _, cost, _ = jax.lax.fori_loop(0, iterations, body, carry)
    return v, cost
