"""The split iteration of the constrained step for a constant kinetic matrix
(`diffrax_vi._step.constrained_engine`): taken where the kinetic matrix is constant, the same root
as the general solve, and the general solve kept elsewhere."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._step import constrained_engine as engine
from diffrax_vi._step import holonomic as holonomic
from tests.helpers import constrained_convergence_order

jax.config.update("jax_enable_x64", True)


def _state_after(problem, degree, h, t1):
    sol = diffrax.diffeqsolve(problem.term, dvi.CGVI(degree), 0.0, t1, h, problem.y0,
                              saveat=diffrax.SaveAt(t1=True, solver_state=True),
                              max_steps=int(round(t1 / h)) + 4)
    return sol.ys[0][-1], sol.ys[1][-1], sol.solver_state.node_values


@pytest.mark.parametrize("degree, h, links", [(2, 0.05, 5), (4, 0.1, 5), (4, 0.025, 20)])
def test_the_split_iteration_converges_to_the_general_solves_root(degree, h, links):
    problem = problems.rigid_chain(n_links=links)
    t = 0.5
    q0, p0, previous = _state_after(problem, degree, h, t)
    t, h = jnp.asarray(t), jnp.asarray(h)

    @jax.jit  # one program: run op by op, these solves took most of the test's time
    def both_solves(q0, p0, previous):
        residual, _ = holonomic._equations(problem.term, degree, t, h, q0, p0, None)
        kinetic = engine.constant_kinetic(problem.term, t, q0, None)
        assert kinetic is not None  # the chain's kinetic matrix is constant: the split step
        start = holonomic._start(problem.term, degree, t, h, q0, p0, None, previous,
                                 velocity=kinetic.velocity)
        scale = 1 + jnp.max(jnp.abs(p0))
        split, updates, converged, finite, _ = engine.split_solve(
            kinetic, degree, t, h, q0, None, problem.term, residual, start, scale)
        newton, *_ = holonomic._newton(residual, start, scale, 100)
        return split, updates, converged, finite, newton, residual(split), scale

    split, updates, converged, finite, newton, (balance, on), scale = both_solves(
        q0, p0, previous)
    assert bool(converged) and bool(finite)
    assert int(updates) <= 15  # a contraction of the engine's rate, not the fallback's cap
    # the same root: the curve to round-off, the impulses to their conditioning
    assert np.max(np.abs(np.asarray(split[0] - newton[0]))) <= 1e-14
    mu = np.max(np.abs(np.asarray(newton[1])))
    assert np.max(np.abs(np.asarray(split[1] - newton[1]))) <= 1e-11 * mu
    assert np.max(np.abs(np.asarray(on))) <= 1e-14
    assert np.max(np.abs(np.asarray(balance))) <= 1e-13 * float(scale)


def test_a_kinetic_matrix_that_moves_keeps_the_general_solve():
    # L = ½ (1 + x²) |v|²: the kinetic matrix depends on q, so no split step
    def lagrangian(t, q, v, args):
        return 0.5 * (1 + q[0] ** 2) * (v @ v) - 9.81 * q[1]

    term = dvi.LagrangianTerm(lagrangian, constraint=lambda t, q, args: (0.5 * (q @ q - 1))[None])
    q0 = jnp.array([jnp.sin(0.5), -jnp.cos(0.5)])
    assert engine.constant_kinetic(term, jnp.asarray(0.0), q0, None) is None
    v0 = 0.7 * jnp.array([jnp.cos(0.5), jnp.sin(0.5)])
    p0 = (1 + q0[0] ** 2) * v0

    order = constrained_convergence_order(term, (q0, p0))
    assert abs(order - 4) < 0.3, order


def test_a_mass_set_by_args_takes_the_split_step_and_is_differentiated():
    # L = ½ m |v|² − m g y with m from `args`: constant in (t, q, v), not known when traced
    def lagrangian(t, q, v, args):
        return args * (0.5 * (v @ v) - 9.81 * q[1])

    term = dvi.LagrangianTerm(lagrangian, constraint=lambda t, q, args: (0.5 * (q @ q - 1))[None])
    q0 = jnp.array([jnp.sin(0.5), -jnp.cos(0.5)])
    assert engine.constant_kinetic(term, jnp.asarray(0.0), q0, jnp.asarray(2.0)) is not None
    v0 = 0.7 * jnp.array([jnp.cos(0.5), jnp.sin(0.5)])

    def end_x(m):
        sol = diffrax.diffeqsolve(term, dvi.CGVI(3), 0.0, 1.0, 0.05, (q0, m * v0), args=m,
                                  saveat=diffrax.SaveAt(t1=True, solver_state=True),
                                  max_steps=32)
        return sol.ys[1][-1, 0], sol.solver_state.holonomic_drift

    (value, drift), grad = jax.value_and_grad(end_x, has_aux=True)(jnp.asarray(2.0))
    assert np.all(np.asarray(drift) <= 1e-13)
    # the motion does not depend on m (p = m v scales with it): d p_x / d m = v_x(T)
    v_end = float(end_x(jnp.asarray(1.0))[0])
    assert abs(float(grad) - v_end) <= 1e-9, (float(grad), v_end)
    assert abs(float(value) - 2 * v_end) <= 1e-12


@pytest.mark.slow
def test_the_20_link_chain_keeps_both_levels_at_round_off():
    problem = problems.rigid_chain(n_links=20)
    sol = diffrax.diffeqsolve(problem.term, dvi.CGVI(4), 0.0, 2.0, 0.025, problem.y0,
                              saveat=diffrax.SaveAt(t1=True, solver_state=True), max_steps=90)
    assert sol.result == diffrax.RESULTS.successful
    assert np.all(np.asarray(sol.solver_state.holonomic_drift) <= 1e-12)
