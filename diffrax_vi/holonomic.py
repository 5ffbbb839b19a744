"""Holonomic constraints in the variational step.

A term with constraints `g(t, q) = 0` (`LagrangianTerm(..., constraint=g)`) is stepped by the
constrained continuous-Galerkin step: the curve is the polynomial of the solver's degree `s`
through its values `Q_1 = q_n, Q_2, ..., Q_{s+1} = q_{n+1}` at the Gauss–Lobatto points, the
action is the Lobatto rule on the same points, and the constraint enters the action with one
multiplier per point,

    S = h Σ_i b_i [L(t_i, Q_i, V_i) − Λ_i·g(t_i, Q_i)],    V_i = (1/h) Σ_j D_ij Q_j,

with the virtual work of a non-conservative force added to its variation. The equations of
one step (unknowns `Q_2..Q_{s+1}` and the impulses `μ_i = h b_i Λ_i`, `i ≤ s`):

- `∂S/∂Q_1 + p_n = 0` and `∂S/∂Q_j = 0` inside the step,
- `g(t_j, Q_j) = 0` at every point after the first (so also at the step's end),

then `p_{n+1} = ∂S/∂Q_{s+1}`, whose last impulse `μ_{s+1}` puts the end state on the hidden
constraint `G(q) v + ∂g/∂t = 0` (`G = ∂g/∂q`, `v` the velocity of `p`). For
`L = ½ vᵀMv − U(q)` this is the Lobatto IIIA–IIIB pair for constrained mechanics (RATTLE for
`s = 1`): symplectic on the constraint's cotangent bundle and of order `2s` (Jay 1996; Hairer,
Lubich & Wanner, *Geometric Numerical Integration*, VII.1), the order of `CGVI(s)`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .ansatz.polynomial import LagrangeBasis, lobatto_points
from .formulation import StepContext, node_momenta_and_forces, stage_values
from .lagrange import lagrange_weights
from .results import STEP_FAILURES

__all__ = [
    "ConstrainedStep", "check_constrained_solver", "constrained_step", "curve_and_forces",
    "drift", "lobatto_rule",
]

# Multiples of the working precision: where the solve stops (the last update this small
# relative to the unknowns' size), and how far a start may sit off the constraint (square
# root of eps relative to its scale, the tolerance of a user-supplied start).
_STOP = 8.0
_HIDDEN_ITERATIONS = 2


@functools.cache
def lobatto_rule(degree: int) -> tuple[tuple[float, ...], np.ndarray, np.ndarray]:
    """`(points, weights, D)` of the Gauss–Lobatto rule with `degree + 1` points on `[0, 1]`:
    the points (`lobatto_points`), their quadrature weights and the differentiation matrix
    `D_ij = ℓ_j'(τ_i)` of the Lagrange polynomials through them. Weights and derivatives are
    computed in extended precision from the float64 points and rounded once."""
    import mpmath

    points = lobatto_points(degree)
    n = len(points)
    with mpmath.workdps(40):
        x = [mpmath.mpf(p) for p in points]
        # ℓ_j(τ) = Π_{m≠j} (τ − x_m) / (x_j − x_m): integrate its monomial coefficients.
        weights, derivative = [], [[mpmath.mpf(0)] * n for _ in range(n)]
        for j in range(n):
            coefficients = [mpmath.mpf(1)]
            denominator = mpmath.mpf(1)
            for m in range(n):
                if m == j:
                    continue
                coefficients = [
                    (coefficients[k - 1] if k > 0 else 0)
                    - x[m] * (coefficients[k] if k < len(coefficients) else 0)
                    for k in range(len(coefficients) + 1)
                ]
                denominator *= x[j] - x[m]
            weights.append(sum(c / (k + 1) for k, c in enumerate(coefficients)) / denominator)
            for i in range(n):
                slope = sum(k * c * x[i] ** (k - 1) for k, c in enumerate(coefficients) if k)
                derivative[i][j] = slope / denominator
        w = np.array([float(v) for v in weights])
        d = np.array([[float(v) for v in row] for row in derivative])
    return points, w, d


class ConstrainedStep(NamedTuple):
    """The solution of one constrained step.

    - `values`: `(s + 1, D)`, the curve's values at the Lobatto points (`values[-1]` is
      `q_{n+1}`).
    - `impulses`: `(s + 1, M)`, the constraint impulses `μ_i = h b_i Λ_i` at the points.
    - `p1`: the end momentum, on the hidden constraint.
    - `iterations`: Newton iterations of the step's solve.
    - `result`: `successful` or the failure (`vi_constraint_unmet`, `vi_step_max_iterations`,
      `vi_step_nonfinite`).
    - `drift`: `(2,)`, `max |g(t_{n+1}, q_{n+1})|` and `max |G v + ∂g/∂t|` at the step's end.
    - `residual`: the size of the last Newton update relative to the unknowns.
    - `tolerance`: where the solve stops (that size at a few ulps).
    """

    values: Array
    impulses: Array
    p1: Array
    iterations: Array
    result: diffrax.RESULTS
    drift: Array
    residual: Array
    tolerance: Array


def _rule(degree: int, dtype):
    points, w, d = lobatto_rule(degree)
    return jnp.asarray(points, dtype), jnp.asarray(w, dtype), jnp.asarray(d, dtype)


def _equations(term, degree, t, h, q0, p0, args):
    """The residual of the step's unknowns `(Q_2..Q_{s+1}, μ_1..μ_s)`, and the map from a
    solution to `(values, p̃_{n+1})` (the end momentum before its last impulse)."""
    tau, b, d = _rule(degree, q0.dtype)
    times = t + tau * h
    jacobian = jax.vmap(term.constraint_jacobian, in_axes=(0, 0, None))

    def momenta(z):
        inner, impulses = z
        values = jnp.concatenate([q0[None], inner])
        velocities = (d @ values) / h
        p, f = jax.vmap(term.momentum_and_force, in_axes=(0, 0, 0, None))(
            times, values, velocities, args
        )
        # ∂S/∂Q_j without the constraint: h b_j f_j + Σ_i b_i D_ij p_i
        sums = d.T @ (b[:, None] * p) + (h * b)[:, None] * f
        return values, sums

    def residual(z):
        inner, impulses = z
        values, sums = momenta(z)
        g = jacobian(times[:-1], values[:-1], args)
        reaction = jnp.einsum("imd,im->id", g, impulses)
        balance = (sums[:-1] - reaction).at[0].add(p0)
        on = jax.vmap(term.constraint_values, in_axes=(0, 0, None))(times[1:], inner, args)
        return balance, on

    return residual, momenta


def _flat(z):
    return jnp.concatenate([z[0].reshape(-1), z[1].reshape(-1)])


def _unflat(x, like):
    n = like[0].size
    return x[:n].reshape(like[0].shape), x[n:].reshape(like[1].shape)


def _newton(residual, start, scale, max_steps):
    """Newton's iteration on `residual` from `start` until its update stops falling at
    round-off: `(z, iterations, converged, finite, last relative update)`."""
    eps = float(jnp.finfo(start[0].dtype).eps)

    def relative(dz, z):
        size_q = jnp.max(jnp.abs(dz[0])) / (1 + jnp.max(jnp.abs(z[0])))
        size_mu = jnp.max(jnp.abs(dz[1]), initial=0.0) / (scale + jnp.max(jnp.abs(z[1]),
                                                                           initial=0.0))
        return jnp.maximum(size_q, size_mu)

    def update(z):
        x = _flat(z)
        r = _flat(residual(z))
        matrix = jax.jacfwd(lambda y: _flat(residual(_unflat(y, z))))(x)
        return _unflat(-jnp.linalg.solve(matrix, r), z)

    def cond(carry):
        z, k, size, previous, done = carry
        return ~done & (k < max_steps)

    def body(carry):
        z, k, _, previous, _ = carry
        dz = update(z)
        z = jax.tree_util.tree_map(jnp.add, z, dz)
        size = relative(dz, z)
        # At round-off the update stops halving: stop there, or once it is a few ulps.
        done = (size <= _STOP * eps) | ((size >= previous / 2) & (size <= eps ** 0.5))
        done = done | ~jnp.isfinite(size)
        return z, k + 1, size, size, done

    inf = jnp.asarray(jnp.inf, start[0].dtype)
    z, k, size, _, done = jax.lax.while_loop(
        cond, body, (start, jnp.array(0, jnp.int32), inf, inf, jnp.array(False))
    )
    finite = jnp.isfinite(size)
    return z, k, done & finite, finite, size


def _hidden(term, t1, q1, p_end, args):
    """The impulse `μ` that puts `p_end − Gᵀμ` on the hidden constraint `G v + ∂g/∂t = 0`
    (Newton from zero; exact after one update where the velocity is linear in `p`)."""
    g = term.constraint_jacobian(t1, q1, args)
    rate = term.constraint_rate(t1, q1, args)

    def hidden(mu):
        return g @ term.velocity(t1, q1, p_end - g.T @ mu, args) + rate

    mu = jnp.zeros(g.shape[0], q1.dtype)
    for _ in range(_HIDDEN_ITERATIONS):
        mu = mu - jnp.linalg.solve(jax.jacfwd(hidden)(mu), hidden(mu))
    return mu, g


def drift(term, t, q, p, args) -> Array:
    """`(max |g(t, q)|, max |G v + ∂g/∂t|)`: how far a state is off the constraint and off
    its hidden (velocity-level) constraint."""
    v = term.velocity(t, q, p, args)
    g = term.constraint_jacobian(t, q, args)
    position = jnp.max(jnp.abs(term.constraint_values(t, q, args)))
    velocity = jnp.max(jnp.abs(g @ v + term.constraint_rate(t, q, args)))
    return jnp.stack([position, velocity])


def check_constrained_solver(basis, error_estimate) -> None:
    """Refuse, by name, what the constrained step cannot do: a basis other than the
    polynomial one, and the companion error estimate."""
    if not isinstance(basis, LagrangeBasis):
        raise ValueError(
            "holonomic constraints are stepped by the polynomial step: use "
            f"diffrax_vi.CGVI(degree) (a LagrangeBasis), not a {type(basis).__name__}"
        )
    if error_estimate is not None:
        raise ValueError(
            "error_estimate is not available with holonomic constraints: use constant steps "
            "(the constrained step has no companion estimate)"
        )


def constrained_step(term, degree: int, t, h, q0, p0, args, max_steps: int) -> ConstrainedStep:
    """One constrained step of degree `degree` from `(q0, p0)` at time `t` over `h`.

    The solve starts from the straight line of the start's velocity with zero impulses, runs
    on values without derivatives, and the step's derivatives are those of its root
    (implicit differentiation of the step's equations)."""
    dtype = q0.dtype
    eps = float(jnp.finfo(dtype).eps)
    tau, b, _ = _rule(degree, dtype)
    m = term.constraint_values(t, q0, args).shape[0]
    scale = 1 + jnp.max(jnp.abs(p0))

    frozen = jax.tree_util.tree_map(
        lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, (t, h, q0, p0, args)
    )
    residual_frozen, _ = _equations(term, degree, *frozen)
    v0 = term.velocity(frozen[0], frozen[2], frozen[3], frozen[4])
    start = (frozen[2] + (tau[1:, None] * frozen[1]) * v0, jnp.zeros((degree, m), dtype))
    found, iterations, converged, finite, size = _newton(
        residual_frozen, start, jax.lax.stop_gradient(scale), max_steps
    )

    residual, momenta = _equations(term, degree, t, h, q0, p0, args)

    def tangent_solve(linear, rhs):
        flat_rhs = _flat(rhs)
        matrix = jax.jacfwd(lambda y: _flat(linear(_unflat(y, rhs))))(jnp.zeros_like(flat_rhs))
        return _unflat(jnp.linalg.solve(matrix, flat_rhs), rhs)

    z = jax.lax.custom_root(residual, found, lambda _, __: found, tangent_solve)
    values, sums = momenta(z)
    t1 = t + h
    q1 = values[-1]
    mu_end, _ = _hidden(term, t1, q1, sums[-1], args)
    p1 = sums[-1] - term.constraint_jacobian(t1, q1, args).T @ mu_end
    impulses = jnp.concatenate([z[1], mu_end[None]])

    start_drift = drift(term, t, q0, p0, args)
    end_drift = drift(term, t1, q1, p1, args)
    v_scale = 1 + jnp.max(jnp.abs(term.velocity(t, q0, p0, args)))
    q_scale = 1 + jnp.max(jnp.abs(q0))
    tolerance = eps ** 0.5 * jnp.stack([q_scale, v_scale])
    unmet = jnp.any(start_drift > tolerance) | jnp.any(end_drift > tolerance)
    result = diffrax.RESULTS.where(
        converged, diffrax.RESULTS.successful, STEP_FAILURES["vi_step_max_iterations"]
    )
    result = diffrax.RESULTS.where(finite, result, STEP_FAILURES["vi_step_nonfinite"])
    result = diffrax.RESULTS.where(
        unmet & finite, STEP_FAILURES["vi_constraint_unmet"], result
    )
    return ConstrainedStep(values, impulses, p1, iterations, result,
                           jax.lax.stop_gradient(end_drift), size, jnp.asarray(_STOP * eps))


def curve_and_forces(solved: ConstrainedStep, basis: LagrangeBasis, ctx: StepContext
                     ) -> tuple[Array, Array]:
    """`(theta, forces)` for the dense output of a constrained step: the curve in the
    basis's own parameters (its values at the basis's points), and the forces at the
    quadrature nodes, the system's less the constraint's reaction `Gᵀλ` (the multipliers
    interpolated between the Lobatto points)."""
    dtype = ctx.q0.dtype
    degree = basis.degree
    lobatto = lobatto_points(degree)
    to_basis = jnp.stack([
        lagrange_weights(lobatto, jnp.asarray(x, dtype)) for x in basis.control_points
    ])
    theta = to_basis @ solved.values
    q_nodes, dq_nodes = stage_values(lambda tau: basis.evaluate(theta, tau), ctx.nodes)
    _, forces = node_momenta_and_forces(ctx, q_nodes, dq_nodes)
    _, weights, _ = lobatto_rule(degree)
    multipliers = solved.impulses / (ctx.h * jnp.asarray(weights, dtype))[:, None]
    at_nodes = jax.vmap(lambda c: lagrange_weights(lobatto, c))(ctx.nodes) @ multipliers
    times = ctx.t + ctx.nodes * ctx.h
    gradients = jax.vmap(ctx.term.constraint_jacobian, in_axes=(0, 0, None))(
        times, q_nodes, ctx.args
    )
    return theta, forces - jnp.einsum("imd,im->id", gradients, at_nodes)
