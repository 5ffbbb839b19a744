"""Holonomic constraints: the constrained Galerkin step (`diffrax_vi._step.holonomic`), its
problems (spherical pendulum, rigid chain) and its refusals."""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._step.holonomic import lobatto_rule
from tests.helpers import constrained_convergence_order

jax.config.update("jax_enable_x64", True)


def _solve(problem, solver, t1, n, *, ts=None, **kwargs):
    # The step as an array and one step cap: runs of up to 248 steps share one compiled
    # program.
    saveat = diffrax.SaveAt(t1=ts is None, ts=ts, solver_state=True)
    return diffrax.diffeqsolve(
        problem.term, solver, problem.t0, t1, jnp.asarray((t1 - problem.t0) / n), problem.y0,
        args=problem.args, saveat=saveat, max_steps=max(256, n + 8), **kwargs,
    )


def _end_error(problem, sol, t1):
    q_ref, p_ref = problem.reference(np.array([t1]))
    q, p = np.asarray(sol.ys[0][-1]), np.asarray(sol.ys[1][-1])
    return max(np.max(np.abs(q - q_ref[0])), np.max(np.abs(p - p_ref[0])))


def test_the_lobatto_rule_integrates_to_its_degree_and_differentiates_exactly():
    for degree in (1, 2, 5):
        points, weights, d = lobatto_rule(degree)
        x = np.asarray(points)
        for power in range(2 * degree):  # exact for degree 2s - 1
            assert abs(weights @ x**power - 1 / (power + 1)) < 1e-15
        for power in range(degree + 1):
            slope = power * x ** max(power - 1, 0) if power else np.zeros_like(x)
            assert np.max(np.abs(d @ x**power - slope)) < 1e-13


@pytest.mark.parametrize(
    "degree",
    # degree 3: the same claim as degree 2 at another order (slow; degree 2 keeps it covered)
    [2, pytest.param(3, marks=pytest.mark.slow)],
)
def test_the_spherical_pendulum_converges_at_the_order_of_the_span(degree):
    # Cartesian coordinates with the constraint against the reference in angle coordinates.
    problem = problems.spherical_pendulum()
    t1 = 2.0
    errors = [_end_error(problem, _solve(problem, dvi.CGVI(degree), t1, n), t1) for n in (20, 40)]
    order = np.log2(errors[0] / errors[1])
    assert abs(order - 2 * degree) < 0.3, (errors, order)


def test_the_constraint_holds_to_round_off_and_the_energy_stays_bounded_over_1e5_steps():
    problem = problems.spherical_pendulum()
    n, dt = 100_000, 0.05
    ts = jnp.linspace(0.0, n * dt, 1001)
    sol = diffrax.diffeqsolve(
        problem.term, dvi.CGVI(2), 0.0, n * dt, dt, problem.y0,
        saveat=diffrax.SaveAt(ts=ts, solver_state=True), max_steps=n + 8,
    )
    position, velocity = np.asarray(sol.solver_state.holonomic_drift)
    assert position <= 1e-12 and velocity <= 1e-12
    q, p = sol.ys
    assert np.max(np.abs(np.sum(np.asarray(q) ** 2, axis=1) - 1.0)) <= 1e-12
    energy = np.asarray(jax.vmap(problem.energy)(ts, q, p))
    error = np.abs(energy - energy[0])
    assert error.max() <= 3 * error[: len(ts) // 10].max()
    # the vertical angular momentum is a symmetry of the constrained system
    lz = np.asarray(q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0])
    assert np.max(np.abs(lz - lz[0])) < 1e-11


def test_the_constrained_step_is_time_reversible():
    # the Lobatto pair is symmetric: 20 steps back from the end return to the start
    problem = problems.spherical_pendulum()
    forward = diffrax.diffeqsolve(problem.term, dvi.CGVI(3), 0.0, 1.0, 0.05, problem.y0)
    end = (forward.ys[0][-1], forward.ys[1][-1])
    back = diffrax.diffeqsolve(problem.term, dvi.CGVI(3), 1.0, 0.0, -0.05, end)
    for x, x0 in zip(back.ys, problem.y0, strict=True):
        assert np.max(np.abs(np.asarray(x[-1]) - np.asarray(x0))) < 1e-14


def test_the_dense_output_follows_the_constrained_motion():
    problem = problems.spherical_pendulum()
    t1, n = 1.0, 20
    sol = diffrax.diffeqsolve(
        problem.term, dvi.CGVI(4), 0.0, t1, t1 / n, problem.y0,
        saveat=diffrax.SaveAt(dense=True), max_steps=n + 8,
    )
    ts = np.array([0.0137, 0.3712, 0.8291])
    q_ref, p_ref = problem.reference(ts)
    q, p = jax.vmap(sol.evaluate)(jnp.asarray(ts))
    assert np.max(np.abs(np.asarray(q) - q_ref)) < 1e-8
    assert np.max(np.abs(np.asarray(p) - p_ref)) < 1e-6


@pytest.mark.parametrize(
    "dtype, error, drift",
    # float16: the same claim in another dtype (slow; float32 keeps it covered)
    [(jnp.float32, 1e-5, 1e-6), pytest.param(jnp.float16, 1e-2, 1e-2, marks=pytest.mark.slow)],
)
def test_the_constrained_step_runs_in_low_precision(dtype, error, drift):
    # float16 factorises in float32 (LAPACK has no half precision) and stays float16 outside
    problem = problems.spherical_pendulum(dtype=dtype)
    sol = diffrax.diffeqsolve(
        problem.term, dvi.CGVI(3), dtype(0.0), dtype(2.0), dtype(0.1), problem.y0,
        saveat=diffrax.SaveAt(t1=True, solver_state=True),
    )
    assert sol.ys[0].dtype == dtype and sol.ys[1].dtype == dtype
    q_ref, _ = problem.reference(np.array([2.0]))
    assert np.max(np.abs(np.asarray(sol.ys[0][-1], np.float64) - q_ref[0])) < error
    assert np.all(np.asarray(sol.solver_state.holonomic_drift, np.float64) < drift)


def test_the_damped_chain_matches_its_angle_reference_and_loses_energy():
    problem = problems.rigid_chain(n_links=5, damping=0.05)
    t1, n = 2.0, 80
    ts = jnp.linspace(0.0, t1, n + 1)
    sol = _solve(problem, dvi.CGVI(3), t1, n, ts=ts)
    assert _end_error(problem, sol, t1) < 1e-9
    assert np.all(np.asarray(sol.solver_state.holonomic_drift) <= 1e-12)
    energy = np.asarray(jax.vmap(problem.energy)(ts, *sol.ys))
    assert np.all(np.diff(energy) < 1e-12)  # dissipation only
    assert energy[-1] < energy[0] - 1e-3


def test_the_chain_runs_under_vmap_as_in_a_loop():
    problem = problems.rigid_chain(n_links=5)
    angles = np.array([[0.4, 0.5, 0.6, 0.7, 0.8], [0.1, -0.2, 0.3, -0.1, 0.2],
                       [1.0, 0.9, 0.8, 0.7, 0.6]])
    q0, p0 = problems.chain_angles_to_state((1.0,) * 5, (1.0,) * 5, angles, np.zeros_like(angles))
    solver = dvi.CGVI(2)

    def run(q, p):
        sol = diffrax.diffeqsolve(problem.term, solver, 0.0, 0.5, 0.05, (q, p), max_steps=16)
        return sol.ys[0][-1], sol.ys[1][-1]

    batched = jax.jit(jax.vmap(run))(jnp.asarray(q0), jnp.asarray(p0))
    for i in range(len(angles)):
        single = jax.jit(run)(jnp.asarray(q0[i]), jnp.asarray(p0[i]))
        for b, s in zip(batched, single, strict=True):
            # The same iterations; XLA's batched products sum in another order, so the
            # members agree to rounding (a few ulps a step), not bit for bit.
            np.testing.assert_allclose(b[i], s, rtol=0, atol=1e-13 * np.max(np.abs(s)))


def test_the_gradient_with_respect_to_the_damping_matches_finite_differences():
    problem = problems.rigid_chain(n_links=5, damping=0.05)

    def end_height(c):
        term = eqx.tree_at(lambda t: t.nonconservative_force.damping, problem.term, c)
        sol = diffrax.diffeqsolve(term, dvi.CGVI(2), 0.0, 1.0, 0.05, problem.y0, max_steps=32)
        return sol.ys[0][-1, -1]  # the height of the chain's last mass

    c = jnp.asarray(0.05)
    grad = float(jax.grad(end_height)(c))
    value = jax.jit(end_height)
    step = 1e-5
    fd = (float(value(c + step)) - float(value(c - step))) / (2 * step)
    assert abs(grad - fd) <= 1e-6 * max(1.0, abs(fd)), (grad, fd)


def test_a_moving_constraint_converges_at_the_order_of_the_span():
    # A pendulum whose pivot is shaken sideways: g(t, q) = (|q − a(t)|² − 1)/2 with
    # a(t) = (0.1 sin 3t, 0); the hidden constraint carries ∂g/∂t.
    def lagrangian(t, q, v, args):
        return 0.5 * v @ v - 9.81 * q[1]

    def constraint(t, q, args):
        pivot = jnp.stack([0.1 * jnp.sin(3.0 * t), jnp.zeros_like(t)]).astype(q.dtype)
        d = q - pivot
        return 0.5 * (d @ d - 1.0)[None]

    term = dvi.LagrangianTerm(lagrangian, constraint=constraint)
    # At t = 0 the pivot is at the origin moving at (0.3, 0): the start's velocity is the
    # pivot's plus a swing across the rod, so that the rod's length does not change.
    q0 = jnp.array([jnp.sin(0.5), -jnp.cos(0.5)])
    v0 = jnp.array([0.3, 0.0]) + 0.7 * jnp.array([jnp.cos(0.5), jnp.sin(0.5)])

    order = constrained_convergence_order(term, (q0, v0))
    assert abs(order - 4) < 0.3, order


# -- refusals ----------------------------------------------------------------------------------


def _pendulum_term(constraint):
    return dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 9.81 * q[1],
                              constraint=constraint)


_START = (jnp.array([0.0, -1.0]), jnp.array([1.0, 0.0]))


@pytest.mark.parametrize(
    "constraint, message",
    [
        (lambda t, q, args: q @ q - 1.0, "1-D array"),
        (lambda t, q, args: jnp.stack([q @ q - 1.0, q[0], q[1]]), "1 <= M < D"),
        (lambda t, q, args: (q @ q - 1.0)[None].astype(jnp.float32), "dtype"),
    ],
)
def test_a_constraint_of_the_wrong_shape_or_dtype_is_refused_by_name(constraint, message):
    with pytest.raises(ValueError, match=message):
        diffrax.diffeqsolve(_pendulum_term(constraint), dvi.CGVI(2), 0.0, 0.1, 0.05, _START)


def test_a_constraint_that_is_not_callable_is_refused():
    with pytest.raises(TypeError, match="constraint must be callable"):
        dvi.LagrangianTerm(lambda t, q, v, args: v @ v, constraint=1.0)


def test_an_explicit_solver_refuses_a_constrained_term():
    term = _pendulum_term(lambda t, q, args: (q @ q - 1.0)[None])
    with pytest.raises(Exception, match="explicit diffrax solvers"):
        diffrax.diffeqsolve(term, diffrax.Dopri8(), 0.0, 0.1, 0.05, _START)


def test_a_network_basis_and_the_error_estimate_are_refused_with_constraints():
    term = _pendulum_term(lambda t, q, args: (q @ q - 1.0)[None])
    with pytest.raises(ValueError, match="CGVI"):
        diffrax.diffeqsolve(term, dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 6)), 0.0, 0.1,
                            0.05, _START)
    with pytest.raises(ValueError, match="error_estimate"):
        solver = dataclasses.replace(dvi.CGVI(2), error_estimate=1)
        diffrax.diffeqsolve(term, solver, 0.0, 0.1, 0.05, _START)


def test_a_start_off_the_constraint_fails_with_its_own_result():
    term = _pendulum_term(lambda t, q, args: (q @ q - 1.0)[None])
    off = (jnp.array([0.0, -1.1]), jnp.array([1.0, 0.0]))
    sol = diffrax.diffeqsolve(term, dvi.CGVI(2), 0.0, 0.1, 0.05, off, throw=False)
    assert dvi.failure_kind(sol.result) == "constraint_unmet"
    assert np.all(np.isnan(np.asarray(sol.ys[0])))
    with pytest.raises(Exception, match="holonomic constraint"):
        diffrax.diffeqsolve(term, dvi.CGVI(2), 0.0, 0.1, 0.05, off)
