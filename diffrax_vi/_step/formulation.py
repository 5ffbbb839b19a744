"""The discrete action of one step and the variational equations built from it.

On a step `[t_n, t_n + h]` with local time `τ ∈ [0, 1]` and a quadrature rule `(c_j, b_j)`,
the discrete action of a trial curve `q_h(τ)` is

    A = h Σ_j b_j L(t_n + c_j h, q_h(c_j), q_h'(c_j) / h).

Its gradient with respect to anything the curve depends on (network parameters, endpoint
positions) is the momentum `ϑ = ∂L/∂v` and force `f = ∂L/∂q` at the nodes pulled back through
the stage map `x ↦ (q_h(c_j), q_h'(c_j))` by one vector-Jacobian product:

    ∂A/∂x = Σ_j b_j [ h f_j · ∂q_h(c_j)/∂x + ϑ_j · ∂q_h'(c_j)/∂x ].

For a `LagrangianTerm` this is `jax.grad` of `A`; written through `(ϑ, f)` it also covers
degenerate systems given only by those maps (`IODETerm`). Two formulations turn it into a
square system for one step (each equation sits at the position of "its" unknown, which
matters for the `J + λI` regularisation):

**Free endpoints** (`FreeEndpoints`; the reference's ShallowNet, ShallowNetReversible,
DenseNet, VISE, and classical cGVI): the curve is the ansatz itself, `q_h(τ) = N(τ; θ)`;
unknowns `θ` and `p_{n+1}`; equations

    ∂/∂θ [ p_{n+1}·q_h(1) − p_n·q_h(0) − A(θ) ] = 0,      q_n − q_h(0) = 0,

then `q_{n+1} = q_h(1)`.

**Interpolating endpoints** (`InterpolatingEndpoints`; the reference's ShallowNetAutodiff
pair): `q_h(τ) = (1 − τ) q_n + τ q_{n+1} + τ(1 − τ) N(τ; θ)` passes through both ends for any
`θ`; unknowns `θ` and `q_{n+1}`; equations

    ∂A/∂θ = 0,      p_n + ∂A/∂q_n = 0,

then `p_{n+1} = ∂A/∂q_{n+1}` (the type-1 generating-function form of the discrete
Euler–Lagrange equations, with `L_d(q_n, q_{n+1}) = A` at the stationary `θ`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree

from .._ansatz.base import AbstractBasis
from .._results import from_root_find
from .._root_finder.step_hints import step_options, traits_of
from .._terms import AbstractMechanicalTerm

__all__ = [
    "AbstractFormulation",
    "CurveSamples",
    "FreeEndpoints",
    "InterpolatingEndpoints",
    "SolveOptions",
    "StepContext",
    "StepSolution",
    "action_gradient",
    "jacobian_option",
    "node_momenta_and_forces",
    "residual_scale",
    "stage_values",
]


class StepContext(eqx.Module):
    """Everything the equations of one step depend on (the `args` of the root find).

    `basis` is the ansatz bound to this step (`AbstractBasis.at_step`).
    """

    term: AbstractMechanicalTerm
    basis: AbstractBasis
    t: Array
    h: Array
    q0: Array
    p0: Array
    args: Any
    nodes: Array
    weights: Array


def stage_values(curve: Callable[[Array], Array], nodes: Array) -> tuple[Array, Array]:
    """`(q_h(c_j), q_h'(c_j))` of a curve `τ ↦ q_h(τ)` at every node, each `(R, D)`."""

    def one(tau):
        return jax.jvp(curve, (tau,), (jnp.ones_like(tau),))

    return jax.vmap(one)(nodes)


class CurveSamples(NamedTuple):
    """A curve on the step given by its samples: values and τ-slopes at the nodes (`(R, D)`
    each) and values at `τ = 0, 1` (`(2, D)`), all a projected start needs of it."""

    values: Array
    slopes: Array
    ends: Array

    @classmethod
    def of(cls, curve: Callable[[Array], Array] | CurveSamples, nodes: Array) -> CurveSamples:
        """The samples of `curve` (a function of `τ`, or samples already)."""
        if isinstance(curve, CurveSamples):
            return curve
        q, dq = stage_values(curve, nodes)
        return cls(q, dq, jax.vmap(curve)(jnp.array([0.0, 1.0], nodes.dtype)))


def node_momenta_and_forces(ctx: StepContext, q: Array, dq: Array) -> tuple[Array, Array]:
    """`(ϑ_j, f_j)` at the nodes, from stage positions and τ-derivatives."""
    ts = ctx.t + ctx.nodes * ctx.h
    v = dq / ctx.h
    return jax.vmap(ctx.term.momentum_and_force, in_axes=(0, 0, 0, None))(ts, q, v, ctx.args)


def action_gradient(ctx: StepContext, curve: Callable[[PyTree, Array], Array], x: PyTree) -> PyTree:
    """`∂A/∂x` of the discrete action of the curve `τ ↦ curve(x, τ)`, shaped like `x`."""
    (q, dq), pullback = jax.vjp(lambda x_: stage_values(lambda s: curve(x_, s), ctx.nodes), x)
    p, f = node_momenta_and_forces(ctx, q, dq)
    b = ctx.weights[:, None]
    (grad,) = pullback((ctx.h * b * f, b * p))
    return grad


def residual_scale(ctx: StepContext) -> Array:
    """Size of the step's residual terms: `1 + max(|q_n|, |p_n|)`."""
    return 1 + jnp.maximum(jnp.max(jnp.abs(ctx.q0)), jnp.max(jnp.abs(ctx.p0)))


class SolveOptions(NamedTuple):
    """What a step's nonlinear solve takes from the solver: its root finder, the iteration
    cap, the root find's adjoint, and the bound seed policy (`Seeder`: the all-parameter
    start and fallback, the projected step's restart)."""

    root_finder: optx.AbstractRootFinder
    max_steps: int
    adjoint: optx.AbstractAdjoint
    seeder: Any


class StepSolution(NamedTuple):
    """How a step's solve ended (`AbstractFormulation.solve_step`).

    - `theta`: the converged curve as ansatz parameters;
    - `increments`: `(q_{n+1} − q_n, p_{n+1} − p_n)`, each to the rounding of its own size,
      where the formulation solves in increments (the solver adds them, compensated);
      else `None`;
    - `end`: `(q_{n+1}, p_{n+1})` where the formulation solves for them; else `None`;
    - `forces`: `∂L/∂q` at the nodes of the converged curve where the solve evaluated them
      (for dense output); else `None`;
    - `iterations`, `result` (a diffrax result), `residual` (final `max|F|`), `tolerance`
      (the residual it had to reach; NaN where the root finder has none), `restarted`;
    - `node_values`: what the next step starts from, where the step's solve carries it: the
      forces and momentum offsets at the nodes of its curve where it took the Jacobian-free
      iteration, the constrained step's values and impulses (`holonomic.PreviousStep`);
      else `None`;
    - `drift`: where the term has holonomic constraints, `(max |g|, max |G v + ∂g/∂t|)` at
      the step's end; else `None`.
    """

    theta: Any
    increments: tuple[Array, Array] | None
    end: tuple[Array, Array] | None
    forces: Array | None
    iterations: Array
    result: Any
    residual: Array
    tolerance: Array
    restarted: Array
    node_values: Any = None
    drift: Array | None = None


def jacobian_option(root_finder, formulation: AbstractFormulation, ctx: StepContext):
    """The Jacobian the solver hands its root finder (the hint `jacobian`, a function of the
    unknowns and the step context): the block assembly of `formulation` where the root finder
    asks for it (`"structured"`), or leaves the choice to us (`"auto"`) and the blocks have a
    closed form; else `None`. The context comes in as the root find's `args`, not by closure,
    so that implicit differentiation of the step sees it."""
    mode = traits_of(root_finder).jacobian_mode()
    if mode == "structured" or (
        mode == "auto" and formulation.has_closed_form_jacobian(ctx.basis)
    ):
        return formulation.jacobian
    return None


class AbstractFormulation(eqx.Module):
    """How the ansatz becomes the curve of a step, and which equations fix its unknowns.

    The unknowns are a pair `(θ, e)`: the ansatz parameters and one endpoint quantity
    (`p_{n+1}` for free endpoints, `q_{n+1}` for interpolating ones). `solve_step` solves
    them for one step.

    A formulation that `continues_itself` starts each step from what its last solve left
    (`StepSolution.node_values`, `first_start` before the first step) rather than from the
    seed policy's trajectory seed.
    """

    continues_itself: ClassVar[bool] = False
    # whether a Lagrangian linear in the velocities puts a primary constraint on the step's
    # end state (`_step.degenerate`): not where the step solves constrained equations
    has_primary_constraint: ClassVar[bool] = True

    def first_start(self, ctx: StepContext):
        """What the first step starts from, where the formulation `continues_itself`."""
        del ctx
        return None

    def solve_step(self, ctx: StepContext, seed, options: SolveOptions) -> StepSolution:
        """The step's equations in all the ansatz parameters (the reference's solve), from
        the seed policy's start `seed`, with its fallback."""
        x0, seed_args, fallback = options.seeder.root_find_start(seed)
        jacobian = jacobian_option(options.root_finder, self, ctx)
        hints = dataclasses.replace(
            fallback,
            scale=residual_scale(ctx),
            outputs=lambda x: self.end_state(x, ctx),
            jacobian=None if jacobian is None else lambda x, a: jacobian(x, a[0]),
        )
        sol = optx.root_find(
            lambda x, a: self.residual(x, a[0]), options.root_finder, x0, (ctx, *seed_args),
            options=step_options(hints), max_steps=options.max_steps, adjoint=options.adjoint,
            throw=False,
        )
        traits = traits_of(options.root_finder)
        dtype = ctx.q0.dtype
        read = traits.final_residual(sol.state, dtype)
        if read is None:  # the root finder keeps no residual: evaluated at its end
            f = ravel_pytree(self.residual(sol.value, ctx))[0]
            tolerance = jnp.full((), jnp.nan, dtype)
        else:
            f, ftol = read
            tolerance = (ftol * residual_scale(ctx)).astype(dtype)
        residual = jax.lax.stop_gradient(jnp.max(jnp.abs(f)).astype(dtype))
        return StepSolution(
            theta=sol.value[0], increments=None, end=self.end_state(sol.value, ctx),
            forces=None, iterations=jnp.asarray(sol.stats["num_steps"], jnp.int32),
            result=from_root_find(sol.result), residual=residual, tolerance=tolerance,
            restarted=jnp.asarray(traits.was_restarted(sol.state)),
        )

    def roots_may_drift(self, basis: AbstractBasis) -> bool:
        """Whether the step's roots may not be isolated (all the parameters of a nonlinear
        ansatz), so that the end state can walk off a first-order Lagrangian's constraint."""
        return not basis.linear

    def fixed_span(self, ctx: StepContext):
        """The span the step solves on where it is fixed when the step is traced (the
        projected step on a fixed hidden layer); else `None`."""
        del ctx
        return None

    def position(self, basis: AbstractBasis, theta, q0: Array, q1: Array, tau) -> Array:
        """The trial curve `q_h(τ)` given the parameters and the endpoint positions."""
        raise NotImplementedError

    def dense_position(self, basis: AbstractBasis, theta, q0: Array, q1: Array, tau) -> Array:
        """The curve as dense output shows it: exactly `q_n` at `τ = 0`, `q_{n+1}` at 1."""
        return self.position(basis, theta, q0, q1, tau)

    def residual(self, x: tuple[PyTree, Array], ctx: StepContext) -> tuple[PyTree, Array]:
        raise NotImplementedError

    def end_state(self, x: tuple[PyTree, Array], ctx: StepContext) -> tuple[Array, Array]:
        """`(q_{n+1}, p_{n+1})` from the converged unknowns."""
        raise NotImplementedError

    def unknowns(self, theta, q_end: Array, p_end: Array) -> tuple[PyTree, Array]:
        """The unknowns from parameters and estimates of the end state."""
        raise NotImplementedError

    def fit_targets(self, labels: Array, q0: Array) -> tuple[Array, bool]:
        """What the parameter seed fits on `τ_i = i/N`, and whether the ansatz is multiplied
        by `τ(1 − τ)` there."""
        raise NotImplementedError

    def jacobian(self, x: tuple[PyTree, Array], ctx: StepContext) -> Array | None:
        """The Jacobian of `residual` assembled by blocks, or `None` where this formulation
        and basis have no structured form (the root finder then differentiates)."""
        return None

    def has_closed_form_jacobian(self, basis: AbstractBasis) -> bool:
        """Whether `jacobian` is formed from closed-form derivatives of `basis` (then it is
        much cheaper than differentiating `residual`, and the default root finders use it)."""
        del basis
        return False


class FreeEndpoints(AbstractFormulation):
    """Free-endpoint formulation: unknowns `(θ, p_{n+1})`, continuity as an equation."""

    def position(self, basis, theta, q0, q1, tau):
        del q0, q1
        return basis.evaluate(theta, tau)

    def dense_position(self, basis, theta, q0, q1, tau):
        # Continuity holds to the Newton tolerance; a linear correction of that size makes
        # the dense output hit q_n exactly (q_h(1) = q_{n+1} holds by definition).
        zero = jnp.zeros((), q0.dtype)
        offset = q0 - basis.evaluate(theta, zero)
        return basis.evaluate(theta, tau) + (1 - tau) * offset

    def residual(self, x, ctx):
        theta, p1 = x
        ends = jnp.array([0.0, 1.0], dtype=q_dtype(ctx))
        q_ends, pullback = jax.vjp(
            lambda th: jax.vmap(ctx.basis.evaluate, in_axes=(None, 0))(th, ends), theta
        )
        (boundary,) = pullback(jnp.stack([-ctx.p0, p1]))
        grad = action_gradient(ctx, ctx.basis.evaluate, theta)
        r_theta = jax.tree_util.tree_map(lambda a, g: a - g, boundary, grad)
        return r_theta, ctx.q0 - q_ends[0]

    def end_state(self, x, ctx):
        theta, p1 = x
        return ctx.basis.evaluate(theta, jnp.ones((), q_dtype(ctx))), p1

    def has_closed_form_jacobian(self, basis) -> bool:
        return bool(getattr(basis, "coordinatewise", False) and getattr(basis, "has_jet", False))

    def jacobian(self, x, ctx) -> Array | None:
        """The Jacobian of `residual` by blocks, for a `coordinatewise` basis (else `None`), as
        a dense matrix in the order of `ravel_pytree` (unknowns `(θ, p_{n+1})`, equations
        `(r_θ, continuity)`).

        With stage values `Q_jd = q_d(c_j)`, `V_jd = q_d'(c_j)` and their gradients `A_jd`,
        `B_jd` in `θ_d` (coordinate `d` depends on `θ_d` alone):

            ∂r_θd/∂θ_e = δ_de ∇²ψ_d − Σ_j b_j [A_jd (h ∂f_d/∂q_e A_je + ∂f_d/∂v_e B_je)
                                            + B_jd (∂ϑ_d/∂q_e A_je + ∂ϑ_d/∂v_e B_je / h)]

        where `ψ_d(θ_d) = p_{n+1,d} q_d(1) − p_{n,d} q_d(0) − Σ_j b_j (h f_jd Q_jd + ϑ_jd V_jd)`
        with `(ϑ, f)` held fixed, and the Lagrangian's second derivatives come from one
        `jax.jacfwd` of `(ϑ, f)` per node. Forward mode through the whole residual instead
        pushes all `D·P` tangents through every coordinate: this is `D` times less work in the
        network part.
        """
        basis = ctx.basis
        if not getattr(basis, "coordinatewise", False):
            return None
        theta, p1 = x
        dtype = q_dtype(ctx)
        nodes = ctx.nodes.astype(dtype)
        h = ctx.h
        b = ctx.weights.astype(dtype)
        zero, one = jnp.zeros((), dtype), jnp.ones((), dtype)
        n_nodes = nodes.shape[0]
        # Stage values (R, D), their gradients A, B (R, D, P) in θ_d, and those of q_d(0),
        # q_d(1) (P, D): in closed form where the basis has one, else by autodiff.
        jet = None
        if self.has_closed_form_jacobian(basis):
            jet = basis.jet(theta, jnp.concatenate([nodes, jnp.stack([zero, one])]))
        if jet is not None:
            (q_all, dq_all), (a_all, b_all) = jet.values(), jet.gradients()
            q, dq, A, B = q_all[:n_nodes], dq_all[:n_nodes], a_all[:n_nodes], b_all[:n_nodes]
            grad_start, grad_end = a_all[n_nodes].T, a_all[n_nodes + 1].T
        else:
            (q, dq), (A, B) = _coordinate_stage_jacobians(basis, theta, nodes)
            g = _coordinate_curve(basis)
            grad_end = jax.vmap(jax.grad(g), in_axes=(1, None), out_axes=1)(theta, one)
            grad_start = jax.vmap(jax.grad(g), in_axes=(1, None), out_axes=1)(theta, zero)
        ts = ctx.t + ctx.nodes * h
        v = dq / h

        def mf(t, qj, vj):
            return ctx.term.momentum_and_force(t, qj, vj, ctx.args)

        (p, f), ((pq, pv), (fq, fv)) = jax.vmap(
            lambda t, qj, vj: (mf(t, qj, vj), jax.jacfwd(mf, argnums=(1, 2))(t, qj, vj))
        )(ts, q, v)
        p, f = jax.lax.stop_gradient((p, f))
        # ∇²ψ_d: ψ_d is a weighted sum of values and slopes of q_d at the nodes and ends.
        if jet is not None:
            ends = jnp.zeros((2,) + p.shape[1:], dtype)
            u = jnp.concatenate([-(h * b)[:, None] * f, -ctx.p0[None], p1[None]])
            w = jnp.concatenate([-b[:, None] * p, ends])
            hess = jet.weighted_hessian(u, w)
        else:
            hess = _coordinate_psi_hessian(basis, theta, nodes, h, b, p, f, ctx.p0, p1)
        n_p, dim = theta.shape
        eye = jnp.eye(dim, dtype=dtype)
        # coupling[p, d, q, e] = ∂(Σ_j b_j (h f_jd A_jdp + ϑ_jd B_jdp))/∂θ_qe through (ϑ, f)
        coupling = (
            jnp.einsum("j,jdp,jde,jeq->pdqe", h * b, A, fq, A)
            + jnp.einsum("j,jdp,jde,jeq->pdqe", b, A, fv, B)
            + jnp.einsum("j,jdp,jde,jeq->pdqe", b, B, pq, A)
            + jnp.einsum("j,jdp,jde,jeq->pdqe", b / h, B, pv, B)
        )
        block = jnp.einsum("dpq,de->pdqe", hess, eye) - coupling
        n = n_p * dim
        top = jnp.concatenate(
            [block.reshape(n, n), jnp.einsum("pd,de->pde", grad_end, eye).reshape(n, dim)],
            axis=1,
        )
        bottom = jnp.concatenate(
            [-jnp.einsum("pe,de->dpe", grad_start, eye).reshape(dim, n),
             jnp.zeros((dim, dim), dtype)], axis=1,
        )
        return jnp.concatenate([top, bottom], axis=0)

    def unknowns(self, theta, q_end, p_end):
        del q_end
        return theta, p_end

    def fit_targets(self, labels, q0):
        del q0
        return labels, False


class InterpolatingEndpoints(AbstractFormulation):
    """Interpolating-endpoint formulation: `q_h(τ) = (1−τ) q_n + τ q_{n+1} + τ(1−τ) N(τ; θ)`,
    unknowns `(θ, q_{n+1})`; the curve is exactly continuous from step to step."""

    def position(self, basis, theta, q0, q1, tau):
        return (1 - tau) * q0 + tau * q1 + (tau * (1 - tau)) * basis.evaluate(theta, tau)

    def _gradients(self, x, ctx):
        theta, q1 = x

        def curve(z, tau):
            th, a, b = z
            return self.position(ctx.basis, th, a, b, tau)

        return action_gradient(ctx, curve, (theta, ctx.q0, q1))

    def residual(self, x, ctx):
        g_theta, g_q0, _ = self._gradients(x, ctx)
        return g_theta, ctx.p0 + g_q0

    def end_state(self, x, ctx):
        _, _, g_q1 = self._gradients(x, ctx)
        return x[1], g_q1

    def unknowns(self, theta, q_end, p_end):
        del p_end
        return theta, q_end

    def fit_targets(self, labels, q0):
        n = labels.shape[0] - 1
        tau = (jnp.arange(n + 1, dtype=labels.dtype) / n)[:, None]
        chord = (1 - tau) * q0 + tau * labels[-1]
        return labels - chord, True


def q_dtype(ctx: StepContext):
    return ctx.q0.dtype


def _coordinate_curve(basis: AbstractBasis):
    """One coordinate of a `coordinatewise` basis: `(θ_d, τ) ↦ q_d(τ)`."""

    def g(theta_d, tau):
        return basis.evaluate(theta_d[:, None], tau)[0]

    return g


def _coordinate_stages(basis: AbstractBasis, nodes: Array):
    """`θ_d ↦ (q_d(c_j), q_d'(c_j))` at every node, each `(R,)`."""
    g = _coordinate_curve(basis)

    def stages_d(theta_d):
        def one(tau):
            return jax.jvp(lambda s: g(theta_d, s), (tau,), (jnp.ones_like(tau),))

        return jax.vmap(one)(nodes)

    return stages_d


def _coordinate_stage_jacobians(basis: AbstractBasis, theta: Array, nodes: Array):
    """Stage values `(R, D)` and their gradients `(R, D, P)` in `θ_d`, by autodiff."""
    stages_d = _coordinate_stages(basis, nodes)
    return jax.vmap(
        lambda th: (stages_d(th), jax.jacfwd(stages_d)(th)), in_axes=1, out_axes=1
    )(theta)


def _coordinate_psi_hessian(basis, theta, nodes, h, b, p, f, p0, p1) -> Array:
    """`∇²ψ_d` by autodiff, `(D, P, P)`, with
    `ψ_d(θ_d) = p_{n+1,d} q_d(1) − p_{n,d} q_d(0) − Σ_j b_j (h f_jd Q_jd + ϑ_jd V_jd)`."""
    g = _coordinate_curve(basis)
    stages_d = _coordinate_stages(basis, nodes)
    zero, one = jnp.zeros((), nodes.dtype), jnp.ones((), nodes.dtype)

    def psi(theta_d, p_d, f_d, p0_d, p1_d):
        qd, dqd = stages_d(theta_d)
        return p1_d * g(theta_d, one) - p0_d * g(theta_d, zero) - jnp.sum(
            b * (h * f_d * qd + p_d * dqd)
        )

    return jax.vmap(jax.hessian(psi), in_axes=(1, 1, 1, 0, 0))(theta, p, f, p0, p1)
