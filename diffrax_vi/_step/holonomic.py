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

from typing import ClassVar, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._ansatz.polynomial import LagrangeBasis, lobatto_points
from .._lagrange import lagrange_weights
from .._lazy import unless_all_skip
from .._linalg import dense_tangent_solve, solve, unpivoted_inverse
from .._precision import lapack_dtype
from .._results import STEP_FAILURES
from .constrained_engine import constant_kinetic, split_solve
from .formulation import (
    AbstractFormulation,
    StepContext,
    StepSolution,
    node_momenta_and_forces,
    stage_values,
)
from .lobatto import lobatto_arrays, lobatto_rule

__all__ = [
    "ConstrainedGalerkin", "ConstrainedStep", "PreviousStep", "check_constrained_solver",
    "constrained_step", "curve_and_forces", "drift", "lobatto_rule", "no_previous_step",
]

# Where the solve stops: its last update this many ulps of the unknowns' size.
_STOP = 8.0
# Newton updates of the end momentum's last impulse (one is exact for a velocity linear in p).
_HIDDEN_ITERATIONS = 2


class ConstrainedStep(NamedTuple):
    """The solution of one constrained step.

    - `values`: `(s + 1, D)`, the curve's values at the Lobatto points (`values[-1]` is
      `q_{n+1}`).
    - `impulses`: `(s + 1, M)`, the constraint impulses `μ_i = h b_i Λ_i` at the points.
    - `dq`, `dp`: the step's increments `q_{n+1} − q_n` and `p_{n+1} − p_n` (the end
      momentum on the hidden constraint), each rounded at its own size.
    - `iterations`: Newton iterations of the step's solve.
    - `result`: `successful` or the failure (`vi_constraint_unmet`, `vi_step_max_iterations`,
      `vi_step_nonfinite`).
    - `drift`: `(2,)`, `max |g(t_{n+1}, q_{n+1})|` and `max |G v + ∂g/∂t|` at the step's end.
    - `residual`: the size of the last Newton update relative to the unknowns.
    - `tolerance`: where the solve stops (that size at a few ulps).
    """

    values: Array
    impulses: Array
    dq: Array
    dp: Array
    iterations: Array
    result: diffrax.RESULTS
    drift: Array
    residual: Array
    tolerance: Array


def _equations(term, degree, t, h, q0, p0, args):
    """The residual of the step's unknowns `(Q_2 − q_n, ..., Q_{s+1} − q_n; μ_1..μ_s)`, and
    the map from them to `(values, ∂S/∂Q without the constraint, forces)`."""
    tau, b, d = lobatto_arrays(degree, q0.dtype)
    times = t + tau * h

    def momenta(z):
        increments, impulses = z
        # the values as the start plus increments; the velocities from the increments alone
        # (the rows of D sum to zero only up to rounding, which would scale with |q_n|)
        values = jnp.concatenate([q0[None], q0 + increments])
        velocities = (d[:, 1:] @ increments) / h
        p, f = jax.vmap(term.momentum_and_force, in_axes=(0, 0, 0, None))(
            times, values, velocities, args
        )
        # ∂S/∂Q_j without the constraint: h b_j f_j + Σ_i b_i D_ij p_i
        sums = d.T @ (b[:, None] * p) + (h * b)[:, None] * f
        return values, sums, f

    def residual(z):
        values, sums, _ = momenta(z)
        reaction = reactions(term, times[:-1], values[:-1], z[1], args)
        balance = (sums[:-1] - reaction).at[0].add(p0)
        on = jax.vmap(term.constraint_values, in_axes=(0, 0, None))(times[1:], values[1:], args)
        return balance, on

    return residual, momenta


def reactions(term, times, values, impulses, args):
    """`G(t_i, Q_i)ᵀ μ_i` at each point: the constraint's reactions, as the transposed
    derivative of `g` (one pass backwards, not the `M × D` Jacobian)."""

    def one(t, q, mu):
        return jax.vjp(lambda x: term.constraint_values(t, x, args), q)[1](mu)[0]

    return jax.vmap(one)(times, values, impulses)


def _flat(z):
    return jnp.concatenate([z[0].reshape(-1), z[1].reshape(-1)])


def _unflat(x, like):
    n = like[0].size
    return x[:n].reshape(like[0].shape), x[n:].reshape(like[1].shape)


def _newton(residual, start, scale, max_steps):
    """The chord iteration on `residual` from `start`, with the Jacobian formed again
    (Newton's update) wherever an update did not shrink the last one fourfold, until the
    update stops falling at round-off: `(z, iterations, converged, finite, last relative
    update)`. Under `vmap` a Jacobian is formed only while some member needs one."""
    eps = float(jnp.finfo(start[0].dtype).eps)

    def relative(dz, z):
        size_q = jnp.max(jnp.abs(dz[0])) / (1 + jnp.max(jnp.abs(z[0])))
        size_mu = jnp.max(jnp.abs(dz[1]), initial=0.0) / (scale + jnp.max(jnp.abs(z[1]),
                                                                           initial=0.0))
        return jnp.maximum(size_q, size_mu)

    dtype = start[0].dtype
    work = lapack_dtype(dtype)  # LAPACK has no half precision: factorise in float32 there

    def factor(z):
        # QR, not LU: on the CPU turning LU's pivots into a permutation is a loop of a few
        # kernels per row, in every factorisation and every solve.
        matrix = jax.jacfwd(lambda y: _flat(residual(_unflat(y, z))))(_flat(z))
        return jnp.linalg.qr(matrix.astype(work))

    def qr_solve(factors, rhs):
        q, r = factors
        return jax.scipy.linalg.solve_triangular(r, q.T @ rhs, lower=False)

    def cond(carry):
        z, factors, fresh, k, size, done = carry
        return ~done & (k < max_steps)

    def body(carry):
        z, factors, fresh, k, previous, _ = carry
        dz = -qr_solve(factors, _flat(residual(z)).astype(work)).astype(dtype)
        dz = _unflat(dz, z)
        z = jax.tree_util.tree_map(jnp.add, z, dz)
        size = relative(dz, z)
        # At round-off Newton's update stops halving: stop there (a chord update that does
        # not halve is only slow, and the Jacobian is formed again), or at a few ulps.
        done = (size <= _STOP * eps) | (fresh & (size >= previous / 2) & (size <= eps ** 0.5))
        done = done | ~jnp.isfinite(size)
        slow = ~done & (size > previous / 4)
        factors = unless_all_skip(slow, lambda: factor(z), factors)
        return z, factors, slow, k + 1, size, done

    inf = jnp.asarray(jnp.inf, start[0].dtype)
    yes = jnp.array(True)
    z, _, _, k, size, done = jax.lax.while_loop(
        cond, body, (start, factor(start), yes, jnp.array(0, jnp.int32), inf, ~yes)
    )
    finite = jnp.isfinite(size)
    return z, k, done & finite, finite, size


def _hidden(term, t1, q1, p_end, args, g):
    """The impulse `μ` that puts `p_end − Gᵀμ` on the hidden constraint `G v + ∂g/∂t = 0`
    (`G` the constraint's Jacobian at `q1`; Newton from zero, exact after one update where
    the velocity is linear in `p`)."""
    rate = term.constraint_rate(t1, q1, args)

    def hidden(mu):
        return g @ term.velocity(t1, q1, p_end - g.T @ mu, args) + rate

    mu = jnp.zeros(g.shape[0], q1.dtype)
    for _ in range(_HIDDEN_ITERATIONS):
        mu = mu - solve(jax.jacfwd(hidden)(mu), hidden(mu))
    return mu


def _hidden_linear(kinetic, term, t1, q1, p_end, args, g):
    """`_hidden` for a constant kinetic matrix: the velocity is affine in `p`, so the impulse
    solves `G M⁻¹ Gᵀ μ = G v(p_end) + ∂g/∂t` (the small symmetric matrix of the constraints,
    inverted once), refined by one update against the rounding of the first."""
    rate = term.constraint_rate(t1, q1, args)
    work = lapack_dtype(q1.dtype)
    inverse = unpivoted_inverse((g @ kinetic.times_minv(g).T).astype(work)).astype(q1.dtype)

    def hidden(mu):
        return g @ kinetic.velocity(t1, q1, p_end - g.T @ mu, args) + rate

    mu = inverse @ hidden(jnp.zeros(g.shape[0], q1.dtype))
    return mu + inverse @ hidden(mu)


def drift(term, t, q, p, args, velocity=None) -> Array:
    """`(max |g(t, q)|, max |G v + ∂g/∂t|)`: how far a state is off the constraint and off
    its hidden (velocity-level) constraint (`velocity`: the inverse Legendre map, default the
    term's own)."""
    v = (term.velocity if velocity is None else velocity)(t, q, p, args)
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


class PreviousStep(NamedTuple):
    """What the next constrained step starts from: the last step's values and impulses at
    the Lobatto points, its length, and whether there is one (not before the first step,
    nor after a jump of the state)."""

    values: Array
    impulses: Array
    h: Array
    valid: Array


def no_previous_step(term, degree: int, t, q0, args) -> PreviousStep:
    """The `PreviousStep` before the first step."""
    m = term.constraint_values(t, q0, args).shape[0]
    zeros = jnp.zeros((degree + 1, m), q0.dtype)
    return PreviousStep(jnp.zeros((degree + 1, q0.shape[0]), q0.dtype), zeros,
                        jnp.ones((), q0.dtype), jnp.array(False))


def _start(term, degree, t, h, q0, p0, args, previous: PreviousStep, velocity=None):
    """The solve's start: the last step's curve and multipliers continued into this step
    (values of the same polynomials at the new points), or, without a last step, the
    straight line of the start's velocity with zero impulses; values as increments."""
    tau, weights, _ = lobatto_arrays(degree, q0.dtype)
    points = lobatto_points(degree)
    line = (tau[1:, None] * h) * (term.velocity if velocity is None else velocity)(t, q0, p0,
                                                                                   args)
    zero = jnp.zeros(previous.impulses[:-1].shape, q0.dtype)
    continued = jax.vmap(lambda x: lagrange_weights(points, x))(1 + (h / previous.h) * tau)
    values = continued[1:] @ previous.values - q0
    multipliers = continued[:-1] @ (previous.impulses / (previous.h * weights)[:, None])
    impulses = (h * weights[:-1])[:, None] * multipliers
    ok = previous.valid & (h != 0) & (previous.h != 0)
    return jnp.where(ok, values, line), jnp.where(ok, impulses, zero)


def constrained_step(term, degree: int, t, h, q0, p0, args, max_steps: int,
                     previous: PreviousStep) -> ConstrainedStep:
    """One constrained step of degree `degree` from `(q0, p0)` at time `t` over `h`.

    The solve starts from the previous step continued (`_start`), runs on values without
    derivatives, and the step's derivatives are those of its root (implicit
    differentiation of the step's equations)."""
    dtype = q0.dtype
    eps = float(jnp.finfo(dtype).eps)
    scale = 1 + jnp.max(jnp.abs(p0))

    frozen = jax.tree_util.tree_map(
        lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x,
        (t, h, q0, p0, args, previous),
    )
    fixed = jax.tree_util.tree_map(  # the term's own parameters (a damping) too
        lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, term)
    residual_frozen, _ = _equations(fixed, degree, *frozen[:5])
    # For a constant kinetic matrix (decided when traced) the split iteration, Jacobian-free
    # in the node values (`_constrained_engine`), with the general solve from the same start
    # only where it does not contract; else the general solve.
    t_, h_, q0_, _, args_, _ = frozen
    kinetic = constant_kinetic(fixed, t_, q0_, args_)
    velocity = fixed.velocity if kinetic is None else kinetic.velocity
    start = _start(fixed, degree, *frozen, velocity=velocity)
    if kinetic is None:
        found, iterations, converged, finite, size = _newton(
            residual_frozen, start, jax.lax.stop_gradient(scale), max_steps
        )
    else:
        split = split_solve(kinetic, degree, t_, h_, q0_, args_, fixed, residual_frozen, start,
                            jax.lax.stop_gradient(scale))

        def general():
            z, k, ok, fine, last = _newton(residual_frozen, start,
                                           jax.lax.stop_gradient(scale), max_steps)
            return z, k + split[1], ok, fine, last

        found, iterations, converged, finite, size = unless_all_skip(~split[2], general, split)

    residual, momenta = _equations(term, degree, t, h, q0, p0, args)
    z = jax.lax.custom_root(residual, found, lambda _, __: found, dense_tangent_solve)
    values, _, forces = momenta(z)
    tau, b, _ = lobatto_arrays(degree, dtype)
    # The momentum's change as the impulses of the step (the forces by the rule, the
    # constraint's reactions): at the root it is `∂S/∂Q_{s+1} − p_n`, rounded at its own size.
    dp_free = h * (b @ forces) - jnp.sum(
        reactions(term, t + tau[:-1] * h, values[:-1], z[1], args), axis=0)
    t1 = t + h
    q1 = values[-1]
    g_end = term.constraint_jacobian(t1, q1, args)
    if kinetic is None:
        mu_end = _hidden(term, t1, q1, p0 + dp_free, args, g_end)
    else:
        # the kinetic matrix again, of the term as differentiated (a mass set by `args`)
        mu_end = _hidden_linear(constant_kinetic(term, t, q0, args), term, t1, q1,
                                p0 + dp_free, args, g_end)
    dp = dp_free - g_end.T @ mu_end
    p1 = p0 + dp
    impulses = jnp.concatenate([z[1], mu_end[None]])

    # The start was checked as the last step's end: checked here only on the first step and
    # after a jump (where there is no last step).
    def start_drift_now():
        return drift(fixed, t_, q0_, frozen[3], args_, velocity)

    start_drift = unless_all_skip(~frozen[5].valid, start_drift_now, jnp.zeros(2, dtype))
    end_drift = drift(fixed, *jax.lax.stop_gradient((t1, q1, p1)), args_, velocity)
    v_scale = 1 + jnp.max(jnp.abs(velocity(t_, q0_, frozen[3], args_)))
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
    return ConstrainedStep(values, impulses, z[0][-1], dp, iterations, result,
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


class ConstrainedGalerkin(AbstractFormulation):
    """The formulation of a term with holonomic constraints: the constrained Galerkin step of
    the polynomial basis's degree, with one multiplier per Lobatto point (`constrained_step`).

    It continues itself: each step starts from the last step's values and impulses
    continued (`PreviousStep`), not from the seed policy's trajectory seed; its unknowns
    are not ansatz parameters, so the all-parameter solve's hooks do not apply.
    """

    continues_itself: ClassVar[bool] = True
    has_primary_constraint: ClassVar[bool] = False

    def first_start(self, ctx: StepContext) -> PreviousStep:
        return no_previous_step(ctx.term, ctx.basis.degree, ctx.t, ctx.q0, ctx.args)

    def solve_step(self, ctx: StepContext, seed, options) -> StepSolution:
        solved = constrained_step(ctx.term, ctx.basis.degree, ctx.t, ctx.h, ctx.q0, ctx.p0,
                                  ctx.args, options.max_steps, seed.start)
        theta, forces = curve_and_forces(solved, ctx.basis, ctx)
        dtype = ctx.q0.dtype
        ok = solved.result == diffrax.RESULTS.successful
        carried = jax.lax.stop_gradient(
            PreviousStep(solved.values, solved.impulses, ctx.h, ok))
        return StepSolution(
            theta=theta, increments=(solved.dq, solved.dp), end=None, forces=forces,
            iterations=solved.iterations, result=solved.result,
            residual=solved.residual.astype(dtype), tolerance=solved.tolerance.astype(dtype),
            restarted=jnp.array(False), node_values=carried, drift=solved.drift.astype(dtype),
        )

    def roots_may_drift(self, basis) -> bool:
        return False  # the step's roots are isolated

    def position(self, basis, theta, q0, q1, tau):
        return basis.evaluate(theta, tau)
