"""The discrete action and the endpoint equations (`diffrax_vi._step.formulation`), and their
Jacobian by coordinate blocks (`jacobian="structured"`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._quadrature import GaussLegendre
from diffrax_vi._seeding.fit import LeastSquaresFit
from diffrax_vi._step.formulation import (
    FreeEndpoints,
    InterpolatingEndpoints,
    StepContext,
    action_gradient,
    stage_values,
)
from diffrax_vi._terms import LagrangianTerm
from tests.helpers import random_theta as _theta

F64 = jnp.float64


# -- 6. formulation --------------------------------------------------------------------------


def lagrangian(t, q, v, args):
    """Time dependent, position-dependent mass, magnetic term and a potential (D = 2)."""
    mass = 1.0 + 0.3 * jnp.sin(q[0]) ** 2 + 0.1 * t
    magnetic = 0.4 * q[1] * v[0] - 0.2 * q[0] * v[1]
    return 0.5 * mass * v[0] ** 2 + 0.5 * v[1] ** 2 + magnetic - jnp.cos(q[0]) * (1 + q[1] ** 2)


def _context(quad_nodes=5):
    term = LagrangianTerm(lagrangian)
    basis = dvi.ShallowNetBasis(dvi.tanh, 4)
    nodes, weights = GaussLegendre(quad_nodes).nodes_weights(F64)
    return StepContext(
        term=term,
        basis=basis,
        t=jnp.asarray(0.7, F64),
        h=jnp.asarray(0.3, F64),
        q0=jnp.asarray([0.4, -0.2], F64),
        p0=jnp.asarray([0.1, 0.5], F64),
        args=None,
        nodes=nodes,
        weights=weights,
    )


def _discrete_action(ctx, theta, curve=None):
    if curve is None:

        def curve(tau):
            return ctx.basis.evaluate(theta, tau)

    total = jnp.zeros((), F64)
    for c, b in zip(ctx.nodes, ctx.weights, strict=True):
        q = curve(c)
        dq = jax.jacfwd(curve)(c)
        total = total + b * lagrangian(ctx.t + c * ctx.h, q, dq / ctx.h, None)
    return ctx.h * total


def test_stage_values_match_basis():
    ctx = _context()
    theta = _theta(4, 2, seed=3)
    q, dq = stage_values(lambda s: ctx.basis.evaluate(theta, s), ctx.nodes)
    assert q.shape == dq.shape == (5, 2)
    for j, c in enumerate(ctx.nodes):
        np.testing.assert_allclose(q[j], ctx.basis.evaluate(theta, c), rtol=1e-15)
        np.testing.assert_allclose(
            dq[j], jax.jacfwd(lambda s: ctx.basis.evaluate(theta, s))(c), rtol=1e-13
        )


@pytest.mark.parametrize("seed", [3, 4])
def test_action_gradient_is_grad_of_discrete_action(seed):
    ctx = _context()
    theta = _theta(4, 2, seed=seed)
    expected = jax.jit(jax.grad(lambda th: _discrete_action(ctx, th)))(theta)
    got = jax.jit(lambda th: action_gradient(ctx, ctx.basis.evaluate, th))(theta)
    assert got.shape == theta.shape
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-12, atol=1e-13)
    assert float(jnp.max(jnp.abs(expected))) > 1e-2  # not a trivially zero comparison


def test_free_endpoints_residual():
    ctx = _context()
    theta = _theta(4, 2, seed=5)
    p1 = jnp.asarray([0.3, -0.8], F64)
    r_theta, r_cont = jax.jit(lambda x: FreeEndpoints().residual(x, ctx))((theta, p1))
    assert r_theta.shape == theta.shape and r_cont.shape == ctx.q0.shape
    zero, one = jnp.zeros((), F64), jnp.ones((), F64)
    np.testing.assert_allclose(
        np.asarray(r_cont), np.asarray(ctx.q0 - ctx.basis.evaluate(theta, zero)), rtol=1e-15
    )

    def boundary_minus_action(th):
        ends = p1 @ ctx.basis.evaluate(th, one) - ctx.p0 @ ctx.basis.evaluate(th, zero)
        return ends - _discrete_action(ctx, th)

    expected = jax.jit(jax.grad(boundary_minus_action))(theta)
    np.testing.assert_allclose(np.asarray(r_theta), np.asarray(expected), rtol=1e-12, atol=1e-13)

    q1, p_end = FreeEndpoints().end_state((theta, p1), ctx)
    np.testing.assert_allclose(q1, ctx.basis.evaluate(theta, one), rtol=1e-15)
    np.testing.assert_array_equal(p_end, p1)


def test_interpolating_endpoints_residual_and_end_momentum():
    ctx = _context()
    theta = _theta(4, 2, seed=6)
    q1 = jnp.asarray([0.45, -0.1], F64)
    form = InterpolatingEndpoints()

    def action(th, a, b):
        return _discrete_action(ctx, th, lambda tau: form.position(ctx.basis, th, a, b, tau))

    g_theta, g_q0, g_q1 = jax.jit(jax.grad(action, argnums=(0, 1, 2)))(theta, ctx.q0, q1)
    r_theta, r_q = jax.jit(lambda x: form.residual(x, ctx))((theta, q1))
    np.testing.assert_allclose(np.asarray(r_theta), np.asarray(g_theta), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(np.asarray(r_q), np.asarray(ctx.p0 + g_q0), rtol=1e-12, atol=1e-13)
    q_end, p_end = form.end_state((theta, q1), ctx)
    np.testing.assert_array_equal(q_end, q1)
    np.testing.assert_allclose(np.asarray(p_end), np.asarray(g_q1), rtol=1e-12, atol=1e-13)
    # The curve passes through both ends for any parameters.
    np.testing.assert_allclose(form.position(ctx.basis, theta, ctx.q0, q1, 0.0), ctx.q0)
    np.testing.assert_allclose(form.position(ctx.basis, theta, ctx.q0, q1, 1.0), q1)

# -- the Jacobian by coordinate blocks (`jacobian="structured"`) ------------------------------
STRUCTURED_CASES = [
    ("harmonic_oscillator", dvi.ShallowNetBasis(dvi.tanh, 6), 8),
    ("double_pendulum", dvi.ShallowNetBasis(dvi.gelu, 5), 6),
    ("pendulum", dvi.ShallowNetBasis(dvi.tanh, 4, symmetry=dvi.MirrorPairs()), 8),
    ("toda_lattice", dvi.ShallowNetBasis(dvi.tanh, 3), 4),
    ("kepler", dvi.LagrangeBasis(4), 5),
]


@pytest.mark.parametrize("name,basis,nodes", STRUCTURED_CASES, ids=[c[0] for c in STRUCTURED_CASES])
def test_structured_jacobian_matches_autodiff(name, basis, nodes):
    from jax.flatten_util import ravel_pytree

    problem = getattr(problems, name)(dtype=F64)
    shallow = isinstance(basis, dvi.ShallowNetBasis)
    seed = {} if shallow else dict(seed=dvi.SeedPolicy(initial_guess=LeastSquaresFit()))
    solver = dvi.NetworkVI(basis, GaussLegendre(nodes), **seed)
    ctx = solver.step_context(problem.term, 0.3, 0.45, problem.y0, problem.args)
    dim = ctx.q0.shape[0]
    theta = 0.5 * jax.random.normal(jax.random.PRNGKey(1), (basis.num_params(), dim), F64)
    x = (theta, ctx.p0 + 0.1)
    flat, unravel = ravel_pytree(x)
    form = FreeEndpoints()
    dense = jax.jit(jax.jacfwd(lambda v: ravel_pytree(form.residual(unravel(v), ctx))[0]))(flat)
    blocks = jax.jit(lambda v: form.jacobian(unravel(v), ctx))(flat)
    assert blocks.shape == dense.shape and blocks.dtype == F64
    np.testing.assert_allclose(blocks, dense, rtol=0, atol=1e-14 * float(jnp.max(jnp.abs(dense))))
    # formulations / bases without the block form say so
    assert InterpolatingEndpoints().jacobian(x, ctx) is None


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float16], ids=lambda d: d.__name__)
def test_structured_jacobian_keeps_the_working_dtype(dtype):
    problem = problems.double_pendulum(dtype=dtype)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 3), GaussLegendre(4))
    ctx = solver.step_context(problem.term, dtype(0.0), dtype(0.1), problem.y0, problem.args)
    theta = jnp.full((solver.basis.num_params(), 2), 0.3, dtype)
    fn = lambda th: FreeEndpoints().jacobian((th, ctx.p0), ctx)
    assert jax.jit(fn)(theta).dtype == dtype
    assert "f64" not in str(jax.make_jaxpr(fn)(theta))
