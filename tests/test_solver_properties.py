"""Property-based: random initial conditions and step sizes never give NaN with a successful
result (a solve either succeeds with finite values or says it failed)."""

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import diffrax_vi as dvi
from diffrax_vi import problems

STEPS = 3
SETTINGS = settings(
    max_examples=8, deadline=None, derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)  # fmt: skip


def make_run(problem, solver):
    @eqx.filter_jit
    def jitted(y0, dt):
        return diffrax.diffeqsolve(
            problem.term, solver, 0.0, STEPS * dt, dt, y0, args=problem.args,
            saveat=diffrax.SaveAt(steps=True), throw=False, max_steps=STEPS + 2,
        )  # fmt: skip

    def run(y0, dt):
        # An array, not a Python float: filter_jit would compile once per step size.
        return jitted(y0, jnp.asarray(dt, y0[0].dtype))

    return run


def check(sol):
    q, p = (np.asarray(a) for a in sol.ys)
    saved = np.isfinite(np.asarray(sol.ts))  # unsaved slots are inf by diffrax's convention
    if sol.result == diffrax.RESULTS.successful:
        assert np.all(np.isfinite(q[saved])) and np.all(np.isfinite(p[saved]))
    else:
        assert dvi.failure_kind(sol.result) != "ok"


@pytest.fixture(scope="module")
def oscillator():
    problem = problems.harmonic_oscillator()
    solver = dvi.ShallowNet(dvi.ShallowNetBasis(dvi.tanh, 6), dvi.GaussLegendre(6))
    return make_run(problem, solver)


@pytest.fixture(scope="module")
def pendulum():
    problem = problems.pendulum()
    solver = dvi.ShallowNet(dvi.ShallowNetBasis(dvi.tanh, 6), dvi.GaussLegendre(6))
    return make_run(problem, solver), problem.params


finite = dict(allow_nan=False, allow_infinity=False)


@SETTINGS
@given(
    q0=st.floats(-3.0, 3.0, **finite),
    p0=st.floats(-3.0, 3.0, **finite),
    dt=st.floats(1e-3, 2.0, **finite),
)
def test_oscillator_never_nan_with_success(oscillator, q0, p0, dt):
    check(oscillator((jnp.array([q0]), jnp.array([p0])), dt))


@pytest.mark.long
@SETTINGS
@given(
    theta=st.floats(-np.pi, np.pi, **finite),
    omega=st.floats(-2.0, 2.0, **finite),
    dt=st.floats(1e-3, 1.0, **finite),
)
def test_pendulum_never_nan_with_success(pendulum, theta, omega, dt):
    run, params = pendulum
    ml2 = params["m"] * params["l"] ** 2
    y0 = (jnp.array([theta, omega]), jnp.array([ml2 * omega, 0.0]))
    check(run(y0, dt))
