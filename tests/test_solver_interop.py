"""NetworkVI behaves like any diffrax solver: output, events, vmap, gradients, controllers,
progress meters, statistics, and the same term in diffrax's own solvers."""

import math
from functools import partial

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from tests.helpers import shallow_network

OMEGA = math.sqrt(0.5)


def oscillator(t, q, v, k):
    """`v²/2 − k q²/2`, the stiffness `k` passed as diffrax's `args`."""
    return 0.5 * v @ v - 0.5 * k * q @ q


TERM = dvi.LagrangianTerm(oscillator)
Y0 = (jnp.array([0.5]), jnp.array([0.0]))


def exact(ts, k=0.5, q0=0.5, p0=0.0):
    w = np.sqrt(k)
    ts = np.asarray(ts)
    return q0 * np.cos(w * ts) + p0 / w * np.sin(w * ts), -q0 * w * np.sin(w * ts) + p0 * np.cos(
        w * ts
    )


solver = partial(shallow_network, dvi.tanh, 10, 8)


SOLVER = solver()


def solve(t0=0.0, t1=1.0, dt0=0.1, y0=Y0, args=0.5, **kwargs):
    return diffrax.diffeqsolve(TERM, SOLVER, t0, t1, dt0, y0, args=args, **kwargs)


# -- output ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "saveat",
    [
        dict(t0=True, t1=True),
        dict(ts=(0.05, 0.5, 0.93)),
        dict(steps=True),
        dict(t0=True, ts=(0.25, 0.75), dense=True),
        dict(t1=True, steps=True, dense=True),
    ],
    ids=["t0-t1", "ts", "steps", "t0-ts-dense", "t1-steps-dense"],
)
def test_saveat_combinations(saveat):
    kwargs = dict(saveat)
    if "ts" in kwargs:
        kwargs["ts"] = jnp.asarray(kwargs["ts"])
    sol = solve(saveat=diffrax.SaveAt(**kwargs))
    ts = np.asarray(sol.ts)
    ts = ts[np.isfinite(ts)]
    q_ref, p_ref = exact(ts)
    np.testing.assert_allclose(np.asarray(sol.ys[0])[: len(ts), 0], q_ref, atol=1e-11)
    np.testing.assert_allclose(np.asarray(sol.ys[1])[: len(ts), 0], p_ref, atol=1e-11)
    if kwargs.get("dense"):
        for t in (0.0, 0.33, 0.5, 1.0):
            q, p = sol.evaluate(t)
            np.testing.assert_allclose(q[0], exact(t)[0], atol=1e-11)


def test_evaluate_and_derivative_of_the_dense_output():
    sol = solve(saveat=diffrax.SaveAt(steps=True, dense=True))
    # Exact at step ends.
    for k in range(10):
        q, p = sol.evaluate(sol.ts[k])
        np.testing.assert_array_equal(q, sol.ys[0][k])
        np.testing.assert_array_equal(p, sol.ys[1][k])
    # Inside a step: position from the converged network, momentum from the node polynomial.
    for t in (0.031, 0.47, 0.9):
        q, p = sol.evaluate(t)
        q_ref, p_ref = exact(t)
        np.testing.assert_allclose(q[0], q_ref, atol=1e-11)
        np.testing.assert_allclose(p[0], p_ref, atol=1e-10)
        dq, dp = sol.derivative(t)
        # The network's own slope: less accurate than its values (measured 2.3e-10; the
        # all-parameter step's root manifold moved it by up to 6.1e-7).
        np.testing.assert_allclose(dq[0], p_ref, atol=1e-9)  # q̇ = v = p for unit mass
        np.testing.assert_allclose(dp[0], -0.5 * q_ref, atol=1e-8)  # ṗ = −k q


def test_event_located_through_the_dense_output():
    def crossing(t, y, args, **kwargs):
        return y[0][0]

    event = diffrax.Event(crossing, root_finder=optx.Newton(rtol=1e-13, atol=1e-13))
    sol = solve(t1=5.0, event=event, saveat=diffrax.SaveAt(t1=True))
    assert sol.result == diffrax.RESULTS.event_occurred
    t_star = math.pi / (2 * OMEGA)
    # Located on the dense output, whose positions are accurate to ~1e-11 (measured 1.9e-10
    # in time, where |q̇| = 0.35).
    assert abs(float(sol.ts[-1]) - t_star) < 1e-9
    assert abs(float(sol.ys[0][-1, 0])) < 1e-10


def test_steps_to_given_times_and_backward_in_time():
    ts = jnp.asarray([0.0, 0.07, 0.2, 0.31, 0.5, 0.58, 0.8, 1.0])
    sol = diffrax.diffeqsolve(
        TERM, SOLVER, 0.0, 1.0, None, Y0, args=0.5,
        stepsize_controller=diffrax.StepTo(ts), saveat=diffrax.SaveAt(steps=True),
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(sol.ts)[:7], np.asarray(ts[1:]))
    np.testing.assert_allclose(np.asarray(sol.ys[0])[:7, 0], exact(ts[1:])[0], atol=1e-11)
    # Backward from t = 1 to 0 returns the initial state.
    q1, p1 = exact(1.0)
    back = solve(t0=1.0, t1=0.0, dt0=-0.1, y0=(jnp.array([q1]), jnp.array([p1])))
    np.testing.assert_allclose(back.ys[0][-1, 0], 0.5, atol=1e-11)
    np.testing.assert_allclose(back.ys[1][-1, 0], 0.0, atol=1e-11)


# -- vmap and gradients -----------------------------------------------------------------------


def test_vmap_over_lagrangian_parameters():
    ks = jnp.asarray([0.3, 0.5, 0.8])
    run = eqx.filter_jit(
        jax.vmap(lambda k: solve(args=k, saveat=diffrax.SaveAt(t1=True)).ys[0][-1, 0])
    )
    got = run(ks)
    np.testing.assert_allclose(np.asarray(got), [exact(1.0, k=float(k))[0] for k in ks], atol=1e-11)


def test_gradients_through_the_solve_match_finite_differences():
    def loss(q0, k):
        sol = solve(y0=(q0, jnp.array([0.1])), args=k, saveat=diffrax.SaveAt(t1=True))
        return sol.ys[0][-1, 0] ** 2 + 0.5 * sol.ys[1][-1, 0] ** 2

    q0, k = jnp.array([0.5]), jnp.asarray(0.5)
    g_q0, g_k = eqx.filter_jit(jax.grad(loss, argnums=(0, 1)))(q0, k)

    def exact_loss(q0, k):
        q, p = exact(1.0, k=k, q0=q0, p0=0.1)
        return q**2 + 0.5 * p**2

    eps = 1e-6
    fd_q0 = (exact_loss(0.5 + eps, 0.5) - exact_loss(0.5 - eps, 0.5)) / (2 * eps)
    fd_k = (exact_loss(0.5, 0.5 + eps) - exact_loss(0.5, 0.5 - eps)) / (2 * eps)
    np.testing.assert_allclose(float(g_q0[0]), fd_q0, rtol=1e-6)
    np.testing.assert_allclose(float(g_k), fd_k, rtol=1e-6)
    # ... and central differences of the discrete solve itself.
    f = eqx.filter_jit(loss)
    fd_solve = (f(q0 + eps, k) - f(q0 - eps, k)) / (2 * eps)
    np.testing.assert_allclose(float(g_q0[0]), float(fd_solve), rtol=1e-5)


# -- diffrax's own solvers, controllers, meters and statistics ---------------------------------


@pytest.mark.parametrize("peer", [diffrax.Tsit5(), diffrax.Dopri8(), diffrax.Kvaerno5()])
def test_the_same_term_in_diffrax_solvers(peer):
    sol = diffrax.diffeqsolve(
        TERM, peer, 0.0, 1.0, 0.1, Y0, args=0.5,
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
        saveat=diffrax.SaveAt(t1=True),
    )  # fmt: skip
    np.testing.assert_allclose(sol.ys[0][-1, 0], exact(1.0)[0], atol=1e-8)


def test_adaptive_steps_with_the_companion_error_estimate():
    adaptive = solver(error_estimate=3)
    assert adaptive.error_order(TERM) == 7
    sol = diffrax.diffeqsolve(
        TERM, adaptive, 0.0, 10.0, 0.1, Y0, args=0.5,
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
        saveat=diffrax.SaveAt(t1=True),
    )  # fmt: skip
    assert sol.result == diffrax.RESULTS.successful
    assert 5 <= int(sol.stats["num_accepted_steps"]) < 100  # much larger steps than dt0
    assert abs(float(sol.ys[0][-1, 0]) - exact(10.0)[0]) < 1e-8
    with pytest.raises(ValueError, match="error_estimate"):
        solver(error_estimate=0)


def test_progress_meter_and_statistics():
    sol = solve(
        progress_meter=diffrax.TqdmProgressMeter(refresh_steps=2),
        saveat=diffrax.SaveAt(t1=True, solver_state=True),
    )
    assert sol.result == diffrax.RESULTS.successful
    for key in ("num_steps", "num_accepted_steps", "num_rejected_steps", "max_steps"):
        assert key in sol.stats
    assert int(sol.stats["num_accepted_steps"]) == 10
    state = sol.solver_state
    assert int(state.steps) == 10 and int(jnp.sum(state.histogram)) == 10
    assert int(state.iterations) == int(jnp.sum(state.histogram * jnp.arange(state.histogram.size)))
    # Per-step counts on request.
    logged = diffrax.diffeqsolve(
        TERM, solver(iteration_log=16), 0.0, 1.0, 0.1, Y0, args=0.5,
        saveat=diffrax.SaveAt(t1=True, solver_state=True),
    ).solver_state  # fmt: skip
    per_step = np.asarray(logged.iteration_log)
    assert per_step.shape == (16,) and np.all(per_step[10:] == -1)
    assert per_step[:10].sum() == int(logged.iterations) and np.all(per_step[:10] >= 1)


def test_event_stops_the_pendulum_at_its_first_turning_point():
    from scipy.special import ellipk

    term = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v + jnp.sum(jnp.cos(q)))
    p0 = 0.5
    # Energy p0²/2 = 1 − cos θ_max; the quarter period is K(sin²(θ_max/2)) for unit frequency.
    theta_max = math.acos(1 - p0**2 / 2)
    t_star = float(ellipk(math.sin(theta_max / 2) ** 2))

    def turning(t, y, args, **kwargs):
        return y[1][0]

    event = diffrax.Event(turning, root_finder=optx.Newton(rtol=1e-13, atol=1e-13))
    sol = diffrax.diffeqsolve(
        term, SOLVER, 0.0, 5.0, 0.1, (jnp.array([0.0]), jnp.array([p0])),
        event=event, saveat=diffrax.SaveAt(t1=True),
    )  # fmt: skip
    assert sol.result == diffrax.RESULTS.event_occurred
    assert abs(float(sol.ts[-1]) - t_star) < 1e-8
    assert abs(float(sol.ys[0][-1, 0]) - theta_max) < 1e-8


def test_pid_on_kepler_needs_fewer_steps_than_constant_stepping():
    """Kepler, e = 0.6, one period: adaptive steps reach the tolerance in fewer steps than
    constant steps that end with a larger error (measured: 19 accepted + 7 rejected steps,
    error 2.7e-9, against 32 constant steps with error 7.2e-8 and 64 with 5.5e-9)."""
    problem = dvi.problems.kepler(eccentricity=0.6, t1=2 * math.pi)
    t1 = 2 * math.pi
    q_ref, p_ref = problem.reference(np.array([t1]))

    def error(sol):
        return max(
            float(np.max(np.abs(np.asarray(sol.ys[0][-1]) - q_ref[0]))),
            float(np.max(np.abs(np.asarray(sol.ys[1][-1]) - p_ref[0]))),
        )

    adaptive = diffrax.diffeqsolve(
        problem.term, solver(error_estimate=3), 0.0, t1, 0.1, problem.y0, args=problem.args,
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
        saveat=diffrax.SaveAt(t1=True),
    )  # fmt: skip
    constant = diffrax.diffeqsolve(
        problem.term, SOLVER, 0.0, t1, t1 / 32, problem.y0, args=problem.args,
        saveat=diffrax.SaveAt(t1=True),
    )  # fmt: skip
    attempts = int(adaptive.stats["num_accepted_steps"] + adaptive.stats["num_rejected_steps"])
    assert error(adaptive) <= 1e-6
    assert attempts < 32 and error(adaptive) < error(constant)
