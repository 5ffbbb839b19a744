"""The reference problems: initial data, energies, reference solutions and standard solvers."""

import jax

jax.config.update("jax_enable_x64", True)

import math  # noqa: E402

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from diffrax_vi._terms import IODETerm, LagrangianTerm  # noqa: E402
from diffrax_vi.problems import (  # noqa: E402
    coupled_oscillators,
    double_pendulum,
    harmonic_oscillator,
    pendulum,
)
from tests.helpers import solve_adaptive  # noqa: E402

FACTORIES = [harmonic_oscillator, pendulum, double_pendulum, coupled_oscillators]
H0 = {
    "harmonic_oscillator": 0.0625,
    "pendulum": 0.4,
    "double_pendulum": -40.218179175435154,
}
# Cross-check values of q (and p for the harmonic oscillator) from the reference notes.
CROSS_CHECKS = {
    "harmonic_oscillator": {
        1.0: ([0.38012229853781504], [-0.22968134246639213]),
        10.0: ([0.35267395315422106], None),
        100.0: ([-0.012420428712111074], None),
    },
    "pendulum": {
        1.0: ([1.6295848805115472, 0.95786710606374614], None),
        10.0: ([2.5255921278252411, 1.5596126290295624], None),
    },
    "double_pendulum": {
        1.0: ([0.614904069579241, 0.379818946939384], None),
        10.0: ([0.874678880135091, 0.558503496920444], None),
    },
}


_solve = solve_adaptive


# -- initial data and energies ---------------------------------------------------------------
@pytest.mark.parametrize("factory", FACTORIES)
@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_initial_state_dtype(factory, dtype):
    problem = factory(dtype=dtype)
    q0, p0 = problem.y0
    assert q0.dtype == dtype and p0.dtype == dtype
    assert problem.dtype == dtype
    assert q0.shape == p0.shape == (problem.dim,)
    # the maps and the energy stay in the working precision
    dq, dp = problem.term.vf(problem.t0, problem.y0, problem.args)
    assert dq.dtype == dtype and dp.dtype == dtype
    assert problem.energy(problem.t0, q0, p0).dtype == dtype


@pytest.mark.parametrize("factory", [harmonic_oscillator, pendulum, double_pendulum])
@pytest.mark.parametrize(("dtype", "rtol"), [(jnp.float32, 1e-6), (jnp.float64, 1e-14)])
def test_initial_energy(factory, dtype, rtol):
    problem = factory(dtype=dtype)
    energy = problem.energy(problem.t0, *problem.y0)
    np.testing.assert_allclose(float(energy), H0[problem.name], rtol=rtol)


@pytest.mark.parametrize("factory", [harmonic_oscillator, double_pendulum, coupled_oscillators])
def test_term_energy_matches_hamiltonian(factory):
    problem = factory(dtype=jnp.float64)
    rng = np.random.default_rng(0)
    qs = jnp.asarray(rng.normal(size=(7, problem.dim)))
    ps = jnp.asarray(rng.normal(size=(7, problem.dim)))
    ts = jnp.zeros(7)
    explicit = jax.vmap(problem.energy)(ts, qs, ps)
    via_term = jax.vmap(lambda t, q, p: problem.term.energy(t, q, p, None))(ts, qs, ps)
    np.testing.assert_allclose(via_term, explicit, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("factory", FACTORIES)
def test_momentum_of_initial_velocity_is_p0(factory):
    problem = factory(dtype=jnp.float64)
    q0, p0 = problem.y0
    v0 = problem.term.velocity(problem.t0, q0, p0, problem.args)
    p = problem.term.momentum(problem.t0, q0, v0, problem.args)
    np.testing.assert_allclose(p, p0, rtol=1e-14, atol=1e-14)


def test_double_pendulum_initial_momentum():
    problem = double_pendulum(dtype=jnp.float64)
    q0, p0 = problem.y0
    np.testing.assert_allclose(q0, [math.pi / 4, math.pi / 2], rtol=1e-15)
    np.testing.assert_allclose(p0, [3.3321622036187746, 7.0685834705770345], rtol=1e-14)
    v0 = jnp.array([0.0, math.pi / 8])
    np.testing.assert_allclose(problem.term.momentum(0.0, q0, v0, None), p0, rtol=1e-14)
    np.testing.assert_allclose(problem.term.velocity(0.0, q0, p0, None), v0, atol=1e-14)
    # passing the momenta directly gives the same problem
    other = double_pendulum(p0=(3.3321622036187746, 7.0685834705770345), dtype=jnp.float64)
    np.testing.assert_allclose(other.y0[1], p0, rtol=1e-15)


def test_double_pendulum_velocity_inverts_momentum():
    problem = double_pendulum(dtype=jnp.float64)
    numerical = LagrangianTerm(problem.term.lagrangian)  # Newton inverse, no closed form
    rng = np.random.default_rng(1)
    for _ in range(5):
        q = jnp.asarray(rng.uniform(-3, 3, size=2))
        p = jnp.asarray(rng.normal(scale=5, size=2))
        v = problem.term.velocity(0.0, q, p, None)
        np.testing.assert_allclose(problem.term.momentum(0.0, q, v, None), p, rtol=1e-12)
        np.testing.assert_allclose(numerical.velocity(0.0, q, p, None), v, rtol=1e-12)


def test_pendulum_maps():
    problem = pendulum(l=1.5, m=0.7, g=2.0, dtype=jnp.float64)
    term = problem.term
    assert isinstance(term, IODETerm)
    q0, p0 = problem.y0
    np.testing.assert_allclose(q0, [math.acos(0.4), 0.0], rtol=1e-15)
    np.testing.assert_allclose(p0, [0.0, 0.0])
    # the maps are the Euler–Lagrange maps of the (degenerate) phase-space Lagrangian
    ml2, mgl = 0.7 * 1.5**2, 0.7 * 2.0 * 1.5

    def lagrangian(t, q, v, args):
        return ml2 * q[1] * v[0] - (0.5 * ml2 * q[1] ** 2 + mgl * jnp.cos(q[0]))

    degenerate = LagrangianTerm(lagrangian)
    rng = np.random.default_rng(2)
    for _ in range(3):
        q, v = jnp.asarray(rng.normal(size=2)), jnp.asarray(rng.normal(size=2))
        for got, want in zip(
            term.momentum_and_force(0.0, q, v, None),
            degenerate.momentum_and_force(0.0, q, v, None),
            strict=True,
        ):
            np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)
        p = term.momentum(0.0, q, v, None)
        np.testing.assert_allclose(
            problem.energy(0.0, q, p), 0.5 * p[0] ** 2 / ml2 + mgl * math.cos(q[0]), rtol=1e-14
        )
    # velocity map: (q₂, (g/l) sin q₁)
    q = jnp.array([0.3, -0.2])
    np.testing.assert_allclose(
        term.velocity(0.0, q, jnp.zeros(2), None), [-0.2, 2.0 / 1.5 * math.sin(0.3)], rtol=1e-15
    )


# -- reference solutions -----------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(CROSS_CHECKS))
def test_reference_cross_checks(name):
    problem = {"harmonic_oscillator": harmonic_oscillator, "pendulum": pendulum}.get(
        name, double_pendulum
    )(dtype=jnp.float64)
    times = sorted(CROSS_CHECKS[name])
    q, p = problem.reference(times)
    assert q.shape == p.shape == (len(times), problem.dim)
    assert q.dtype == p.dtype == np.float64
    rtol = 1e-14 if problem.reference_method == "closed form" else 1e-10
    for i, t in enumerate(times):
        q_want, p_want = CROSS_CHECKS[name][t]
        np.testing.assert_allclose(q[i], q_want, rtol=rtol, atol=1e-15)
        if p_want is not None:
            np.testing.assert_allclose(p[i], p_want, rtol=rtol)


def test_pendulum_reference_momentum():
    problem = pendulum(dtype=jnp.float64)
    q, p = problem.reference(np.linspace(0.0, 3.0, 7))
    np.testing.assert_allclose(p[:, 0], q[:, 1], rtol=1e-12, atol=1e-14)  # m l² θ̇
    np.testing.assert_array_equal(p[:, 1], 0.0)
    energy = jax.vmap(problem.energy)(jnp.zeros(7), jnp.asarray(q), jnp.asarray(p))
    np.testing.assert_allclose(energy, 0.4, rtol=1e-12)


def test_harmonic_oscillator_general_initial_data():
    problem = harmonic_oscillator(m=2.0, k=3.0, q0=-0.2, p0=0.7, t0=1.0, t1=2.0, dtype=jnp.float64)
    omega = math.sqrt(1.5)
    ts = np.array([1.0, 1.3, 2.0, -0.5])
    q, p = problem.reference(ts)
    tau = ts - 1.0
    c, s = np.cos(omega * tau), np.sin(omega * tau)
    np.testing.assert_allclose(q[:, 0], -0.2 * c + 0.7 / (2.0 * omega) * s, rtol=1e-14)
    np.testing.assert_allclose(p[:, 0], 2.0 * (0.2 * omega * s + 0.7 / 2.0 * c), rtol=1e-14)
    energy = p[:, 0] ** 2 / 4.0 + 1.5 * q[:, 0] ** 2
    np.testing.assert_allclose(energy, energy[0], rtol=1e-14)


def test_reference_memoised_and_ordered():
    problem = double_pendulum(dtype=jnp.float64)
    ts = np.array([0.5, 0.0, 1.0, -0.5, 0.25])
    q, p = problem.reference(ts)
    np.testing.assert_array_equal(q[1], problem.y0[0])
    flow = problem.reference_flow.fallback  # DOP853 serves the time before t0
    assert len(flow._cache) == 1
    q_again, _ = problem.reference(ts)
    assert len(flow._cache) == 1
    np.testing.assert_array_equal(q_again, q)
    q_again[:] = 0.0  # the caller's copy, not the cache
    np.testing.assert_array_equal(problem.reference(ts)[0], q)
    # points agree with separately computed ones; backward times integrate backwards
    for i, t in enumerate(ts):
        np.testing.assert_allclose(problem.reference([t])[0][0], q[i], rtol=1e-10, atol=1e-12)
    # the energy is conserved along the reference in both directions
    energy = jax.vmap(problem.energy)(jnp.asarray(ts), jnp.asarray(q), jnp.asarray(p))
    np.testing.assert_allclose(energy, H0["double_pendulum"], rtol=1e-11)


def test_coupled_oscillators_uncoupled_closed_form():
    problem = coupled_oscillators(
        coupling=0.0, q0=(0.5, -0.3), p0=(0.0, 0.4), t1=0.3, dt=0.1, dtype=jnp.float64
    )
    assert problem.reference_method == "closed form" and problem.n_steps == 3
    q, _ = problem.reference(problem.ts)
    w = np.sqrt(np.array([1.5 / 2.0, 0.3 / 1.0]))
    t = problem.ts[:, None]
    want = np.array([0.5, -0.3]) * np.cos(w * t) + np.array([0.0, 0.4]) / w * np.sin(w * t)
    np.testing.assert_allclose(q, want, rtol=1e-14, atol=1e-15)
    ys = _solve(problem, diffrax.Dopri8(), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ys[0], q, rtol=1e-10, atol=1e-12)


# -- standard diffrax solvers on the terms -------------------------------------------------------
CASES = [
    (harmonic_oscillator, {}),
    (pendulum, {}),
    (double_pendulum, {"t1": 1.0, "dt": 0.1}),
    (coupled_oscillators, {"t1": 2.0, "dt": 0.4}),
]


@pytest.mark.parametrize(("factory", "span"), CASES)
@pytest.mark.parametrize(
    ("solver", "rtol", "atol", "tol"),
    [(diffrax.Tsit5(), 1e-10, 1e-12, 1e-9), (diffrax.Dopri8(), 1e-12, 1e-14, 1e-11)],
    ids=["Tsit5", "Dopri8"],
)
def test_standard_solvers_reproduce_reference(factory, span, solver, rtol, atol, tol):
    problem = factory(dtype=jnp.float64)
    problem = problem.with_span(**span) if span else problem
    q, p = _solve(problem, solver, rtol, atol)
    q_ref, p_ref = problem.reference(problem.ts)
    scale_q, scale_p = np.abs(q_ref).max(), max(np.abs(p_ref).max(), 1.0)
    assert np.abs(np.asarray(q) - q_ref).max() / scale_q < tol
    assert np.abs(np.asarray(p) - p_ref).max() / scale_p < tol


def test_float32_tsit5_stays_float32():
    problem = double_pendulum(t1=1.0, dt=0.1, dtype=jnp.float32)
    q, p = _solve(problem, diffrax.Tsit5(), rtol=1e-6, atol=1e-6)
    assert q.dtype == p.dtype == jnp.float32
    q_ref, _ = problem.reference(problem.ts)
    np.testing.assert_allclose(q, q_ref, rtol=1e-4, atol=1e-4)


def test_float32_pendulum_tsit5():
    problem = pendulum(dtype=jnp.float32)
    q, p = _solve(problem, diffrax.Tsit5(), rtol=1e-6, atol=1e-6)
    assert q.dtype == p.dtype == jnp.float32
    np.testing.assert_allclose(q[-1], CROSS_CHECKS["pendulum"][1.0][0], rtol=1e-5)


# -- spans -----------------------------------------------------------------------------------------
def test_spans():
    problem = double_pendulum()
    assert (problem.t0, problem.t1, problem.dt, problem.n_steps) == (0.0, 10.0, 0.01, 1000)
    short = problem.with_span(1.0, dt=0.1)
    assert (short.t1, short.dt, short.n_steps) == (1.0, 0.1, 10)
    np.testing.assert_allclose(short.ts, np.linspace(0.0, 1.0, 11), rtol=1e-15, atol=1e-15)
    assert short.ts[-1] == 1.0
    bench = harmonic_oscillator().with_span(dt=10.0, n_steps=10)
    assert (bench.t1, bench.dt) == (100.0, 10.0)
    assert problem.y0 is short.y0 and problem.term is short.term
    with pytest.raises(ValueError, match="whole steps"):
        _ = problem.with_span(1.0, dt=0.3).n_steps
    with pytest.raises(ValueError, match="forwards"):
        problem.with_span(-1.0)
    with pytest.raises(ValueError, match="positive"):
        problem.with_span(dt=0.0)
    with pytest.raises(ValueError, match="either"):
        problem.with_span(1.0, n_steps=3)
    assert "double_pendulum" in repr(problem)


def test_argument_validation():
    with pytest.raises(ValueError, match="floating"):
        harmonic_oscillator(dtype=jnp.int32)
    with pytest.raises(ValueError, match="2 component"):
        double_pendulum(q0=(0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match="positive"):
        pendulum(l=-1.0)
    with pytest.raises(ValueError, match="p0"):
        harmonic_oscillator(q0=(0.1, 0.2), p0=(0.0,))


def test_problem_is_jit_friendly():
    problem = double_pendulum(dtype=jnp.float32)
    energy = jax.jit(jax.vmap(problem.energy))(
        jnp.zeros(3, jnp.float32), jnp.stack([problem.y0[0]] * 3), jnp.stack([problem.y0[1]] * 3)
    )
    assert energy.dtype == jnp.float32
    np.testing.assert_allclose(energy, H0["double_pendulum"], rtol=1e-6)
    # the term (with its baked-in parameters) is a pytree that jit can take as an argument
    vf = jax.jit(lambda term, y: term.vf(0.0, y, None))(problem.term, problem.y0)
    assert vf[0].dtype == vf[1].dtype == jnp.float32
