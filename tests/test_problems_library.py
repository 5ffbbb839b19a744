"""The extended problem library: Toda, Hénon–Heiles, perturbed pendulum, outer solar system,
Kepler; their invariants and their stored (or exact) reference solutions (also those of the
basic pendulum, double pendulum and coupled oscillators)."""

import jax

jax.config.update("jax_enable_x64", True)

import math  # noqa: E402

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from diffrax_vi.problems import (  # noqa: E402
    Problem,
    coupled_oscillators,
    double_pendulum,
    henon_heiles,
    kepler,
    outer_solar_system,
    pendulum,
    perturbed_pendulum,
    toda_lattice,
)
from diffrax_vi.problems.kepler import solve_kepler_equation  # noqa: E402
from diffrax_vi.problems.toda_lattice import bump_initial_condition  # noqa: E402
from tests.helpers import check_stored_data, solve_adaptive  # noqa: E402

FACTORIES = [toda_lattice, henon_heiles, perturbed_pendulum, outer_solar_system, kepler]
STORED = [
    toda_lattice,
    henon_heiles,
    perturbed_pendulum,
    outer_solar_system,
    pendulum,
    double_pendulum,
    coupled_oscillators,
]
# initial energies quoted by the reference notes (rtol: the digits quoted)
H0 = {
    "toda_lattice": (10.423704531565422, 1e-14),
    "henon_heiles": (0.135333, 3e-6),
    "perturbed_pendulum": (-0.2193956, 3e-7),
    "kepler": (-0.5, 1e-15),
}
# max-norm accuracy of the stored flows (what the generator verified, with a margin)
STORED_ACCURACY = {
    "toda_lattice": 5e-15,
    "henon_heiles": 2e-15,
    "perturbed_pendulum": 2e-15,
    "outer_solar_system": 1e-14,
    "pendulum": 3e-15,
    "double_pendulum": 5e-14,  # |p| reaches 48
    "coupled_oscillators": 6e-15,
}
# relative agreement with scipy's DOP853 (rtol 1e-13) over the default span; the double pendulum
# is chaotic, so over its span (0, 10) DOP853 itself is good to ~1e-11 only (measured: 8e-12)
DOP853_AGREEMENT = {"double_pendulum": 3e-11}


def _solve(problem: Problem, solver, rtol, atol):
    q, p = solve_adaptive(problem, solver, rtol, atol)
    return np.asarray(q), np.asarray(p)


def _invariants_along(problem: Problem, q: np.ndarray, p: np.ndarray) -> dict[str, np.ndarray]:
    ts = jnp.zeros(q.shape[0])
    return {
        name: np.asarray(jax.vmap(fn, in_axes=(0, 0, 0, None))(ts, q, p, problem.args))
        for name, fn in problem.invariants.items()
    }


# -- construction, dtypes, energies ----------------------------------------------------------------
@pytest.mark.parametrize("factory", FACTORIES)
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_builds_in_dtype(factory, dtype):
    problem = factory(dtype=dtype)
    q0, p0 = problem.y0
    assert q0.dtype == p0.dtype == dtype
    assert q0.shape == p0.shape == (problem.dim,)
    dq, dp = problem.term.vf(problem.t0, problem.y0, problem.args)
    assert dq.dtype == dp.dtype == dtype
    assert problem.energy(problem.t0, q0, p0).dtype == dtype
    assert "energy" in problem.invariants
    for fn in problem.invariants.values():
        assert jnp.result_type(fn(problem.t0, q0, p0, problem.args)) == dtype
    problem.n_steps  # noqa: B018 - dt divides the default span


@pytest.mark.parametrize("name", sorted(H0))
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_initial_energy(name, dtype):
    factory = {f.__name__: f for f in FACTORIES}[name]
    problem = factory(dtype=dtype)
    value, rtol = H0[name]
    energy = float(problem.energy(problem.t0, *problem.y0))
    np.testing.assert_allclose(energy, value, rtol=max(rtol, 1e-6 if dtype == jnp.float32 else 0))


def test_initial_energy_exact_values():
    hh = henon_heiles(dtype=jnp.float64)
    want = 0.09 + 0.04 + (0.008 - 0.008 / 3)
    np.testing.assert_allclose(hh.energy(0.0, *hh.y0), want, rtol=1e-15)
    pp = perturbed_pendulum(dtype=jnp.float64)
    a = 0.3 * 0.5 * math.sin(2 * math.pi / 3) + 0.7 * 0.5 * math.sin(math.pi)
    np.testing.assert_allclose(pp.params["A"], a, rtol=1e-15)
    np.testing.assert_allclose(pp.energy(0.0, *pp.y0), -0.25 * math.cos(0.5), rtol=1e-15)
    # outer solar system: H₀ from the raw data, by hand
    ss = outer_solar_system(dtype=jnp.float64)
    m = np.array([ss.params[f"m_{k}"] for k in range(6)])
    x = np.asarray(ss.y0[0]).reshape(6, 3)
    v = np.asarray(ss.y0[1]).reshape(6, 3) / m[:, None]
    kinetic = 0.5 * np.sum(m[:, None] * v**2)
    potential = sum(
        -ss.params["G"] * m[i] * m[j] / np.linalg.norm(x[i] - x[j])
        for i in range(6)
        for j in range(i)
    )
    np.testing.assert_allclose(ss.energy(0.0, *ss.y0), kinetic + potential, rtol=1e-13)
    np.testing.assert_allclose(v[1], [0.00565429, -0.00412490, -0.00190589], rtol=1e-15)


def test_toda_bump_initial_condition():
    problem = toda_lattice(dtype=jnp.float64)
    want = [0, 0.00675, 0.08575, 0.33175, 0.71875, 0.98575, 0.88525, 0.52225, 0.18225]
    want += [0.03125, 0.00025, 0, 0, 0, 0, 0]
    np.testing.assert_allclose(problem.y0[0], want, atol=1e-14)
    np.testing.assert_array_equal(problem.y0[1], 0.0)
    assert problem.params == {"n": 16, "alpha": 0.64, "mu": 0.3}
    assert bump_initial_condition(40).shape == (40,)
    small = toda_lattice(n=5, dtype=jnp.float32)
    assert small.dim == 5 and small.y0[0].dtype == jnp.float32


@pytest.mark.parametrize("factory", FACTORIES)
def test_term_energy_and_velocity_match(factory):
    problem = factory(dtype=jnp.float64)
    rng = np.random.default_rng(0)
    q0, p0 = (np.asarray(x) for x in problem.y0)
    for _ in range(3):
        q = jnp.asarray(q0 + 0.05 * rng.normal(size=problem.dim))
        p = jnp.asarray(p0 + 0.05 * rng.normal(size=problem.dim) * (np.abs(p0).max() + 1e-3))
        np.testing.assert_allclose(
            problem.term.energy(0.0, q, p, None), problem.energy(0.0, q, p), rtol=1e-12
        )
        v = problem.term.velocity(0.0, q, p, None)
        np.testing.assert_allclose(problem.term.momentum(0.0, q, v, None), p, rtol=1e-12)


# -- stored reference solutions --------------------------------------------------------------------
@pytest.mark.parametrize("factory", STORED)
def test_stored_data_present_and_small(factory):
    problem = factory(dtype=jnp.float64)
    check_stored_data(problem, STORED_ACCURACY[problem.name], max_bytes=100_000)


@pytest.mark.parametrize("factory", STORED)
def test_stored_reference_satisfies_hamiltons_equations(factory):
    problem = factory(dtype=jnp.float64)
    flow = problem.reference_flow
    span = problem.t1 - problem.t0
    spacing = float(flow.data["spacing"])
    rng = np.random.default_rng(1)
    # random times plus times straddling checkpoints and the midpoints between them
    times = np.concatenate(
        [rng.uniform(0.1, 0.9, 8) * span, [spacing * 3, spacing * 3.5, spacing * 10.5]]
    )
    h = 1e-3 * spacing / 0.25
    offsets = np.array([-2, -1, 1, 2]) * h
    q, p = problem.reference(problem.t0 + (times[:, None] + offsets).ravel())
    y = np.concatenate([q, p], axis=1).reshape(times.shape[0], 4, -1)
    derivative = (y[:, 0] - 8 * y[:, 1] + 8 * y[:, 2] - y[:, 3]) / (12 * h)
    q, p = problem.reference(problem.t0 + times)
    want = flow.rhs(np.concatenate([q, p], axis=1))
    scale = np.abs(want).max(axis=0) + 1e-300
    assert np.max(np.abs(derivative - want) / scale) < 1e-8


@pytest.mark.parametrize("factory", STORED)
def test_stored_reference_conserves_invariants(factory):
    problem = factory(dtype=jnp.float64)
    ts = np.linspace(problem.t0, problem.t1, 97)
    q, p = problem.reference(ts)
    assert q.shape == p.shape == (97, problem.dim) and q.dtype == np.float64
    np.testing.assert_array_equal(q[0], problem.y0[0])
    invariants = _invariants_along(problem, q, p)
    if not problem.invariants:  # the basic problems carry only their Hamiltonian
        ts0 = jnp.zeros(q.shape[0])
        invariants["energy"] = np.asarray(jax.vmap(problem.energy)(ts0, q, p))
    for name, values in invariants.items():
        scale = np.abs(values[0]).max() or 1.0  # the Toda momentum vanishes
        if problem.name == "outer_solar_system" and name == "energy":
            scale = 1e-4  # |H| is a tiny difference of kinetic and potential energies
        assert np.max(np.abs(values - values[0])) / scale < 1e-13, name


@pytest.mark.parametrize(
    ("factory", "span"),
    [
        (toda_lattice, {"t1": 2.0, "dt": 0.1}),
        (henon_heiles, {"t1": 2.0}),
        (perturbed_pendulum, {"t1": 2.0}),
        (outer_solar_system, {"t1": 20.0, "dt": 2.0}),
        (pendulum, {}),
        (double_pendulum, {"t1": 1.0, "dt": 0.1}),
        (coupled_oscillators, {"t1": 20.0, "dt": 0.4}),
    ],
)
def test_stored_reference_matches_dopri8(factory, span):
    problem = factory(dtype=jnp.float64).with_span(**span)
    q, p = _solve(problem, diffrax.Dopri8(), rtol=1e-13, atol=1e-16)
    q_ref, p_ref = problem.reference(problem.ts)
    assert np.max(np.abs(q - q_ref)) / np.abs(q_ref).max() < 1e-11
    assert np.max(np.abs(p - p_ref)) / np.abs(p_ref).max() < 1e-11


@pytest.mark.parametrize("factory", STORED)
def test_stored_reference_matches_dop853(factory):
    pytest.importorskip("scipy")
    problem = factory(dtype=jnp.float64)
    flow = problem.reference_flow
    tau = np.linspace(0.0, problem.t1 - problem.t0, 9)[1:]
    q, p = flow(tau)
    q_dop, p_dop = flow.fallback(tau)
    tol = DOP853_AGREEMENT.get(problem.name, 1e-11)
    scale = max(np.abs(q).max(), 1.0)
    np.testing.assert_allclose(q, q_dop, rtol=0, atol=tol * scale)
    np.testing.assert_allclose(p, p_dop, rtol=0, atol=tol * max(np.abs(p).max(), 1e-300))


def test_stored_reference_fallbacks(monkeypatch):
    pytest.importorskip("scipy")
    problem = henon_heiles(dtype=jnp.float64)
    flow = problem.reference_flow
    # outside the stored span (before t0, after t1) DOP853 takes over, inside the data is used
    ts = np.array([-0.5, 0.0, 3.3, 10.0, 10.5])
    q, p = problem.reference(ts)
    q_dop, p_dop = flow.fallback(ts - problem.t0)
    np.testing.assert_allclose(q, q_dop, atol=1e-12)
    np.testing.assert_allclose(p, p_dop, atol=1e-12)
    # a shifted start: the reference depends on the elapsed time only
    shifted = henon_heiles(t0=5.0, t1=15.0, dtype=jnp.float64)
    np.testing.assert_allclose(shifted.reference([8.3])[0], problem.reference([3.3])[0], atol=1e-14)
    # non-default parameters do not use the stored data
    other = henon_heiles(lam=0.5, dtype=jnp.float64)
    assert other.reference_flow.data is None
    q_other, _ = other.reference([1.0])
    assert np.max(np.abs(q_other - problem.reference([1.0])[0])) > 1e-6

    # without scipy, a request outside the data fails with a clear message
    def no_scipy(tau):
        raise ImportError("no scipy")

    monkeypatch.setattr(flow, "fallback", no_scipy)
    with pytest.raises(ImportError, match="stored only for its default problem"):
        problem.reference([11.0])
    problem.reference([1.0])  # inside the span, scipy is not needed


def test_toda_momentum_and_reference_for_other_sizes():
    pytest.importorskip("scipy")
    problem = toda_lattice(n=6, t1=5.0, dtype=jnp.float64)
    assert problem.reference_flow.data is None
    q, p = problem.reference(np.linspace(0.0, 5.0, 6))
    invariants = _invariants_along(problem, q, p)
    np.testing.assert_allclose(invariants["momentum"], 0.0, atol=1e-13)
    np.testing.assert_allclose(invariants["energy"], invariants["energy"][0], rtol=1e-12)


# -- Kepler ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("eccentricity", [0.0, 0.5, 0.9])
def test_kepler_exact_solution(eccentricity):
    e = eccentricity
    problem = kepler(e, dtype=jnp.float64)
    q0, p0 = problem.y0
    np.testing.assert_allclose(q0, [1 - e, 0.0], rtol=1e-15)
    np.testing.assert_allclose(p0, [0.0, math.sqrt((1 + e) / (1 - e))], rtol=1e-15)
    ts = np.linspace(-7.0, 20.0, 271)
    q, p = problem.reference(ts)
    np.testing.assert_allclose(q[ts == 0][0], q0, atol=1e-15)
    # period 2π
    q_period, p_period = problem.reference(ts + 2 * math.pi)
    np.testing.assert_allclose(q_period, q, atol=1e-12)
    np.testing.assert_allclose(p_period, p, atol=1e-11)
    # invariants along the exact solution
    invariants = _invariants_along(problem, q, p)
    np.testing.assert_allclose(invariants["energy"], -0.5, rtol=1e-13)
    np.testing.assert_allclose(invariants["angular_momentum"], math.sqrt(1 - e * e), atol=1e-14)
    np.testing.assert_allclose(invariants["runge_lenz"], np.tile([e, 0.0], (271, 1)), atol=1e-13)
    # Kepler's equation residual
    mean = np.linspace(-50.0, 50.0, 1001)
    ecc = solve_kepler_equation(mean, e)
    np.testing.assert_allclose(ecc - e * np.sin(ecc), mean, rtol=0, atol=1e-13)


@pytest.mark.parametrize("eccentricity", [0.2, 0.7])
def test_kepler_exact_matches_dopri8(eccentricity):
    problem = kepler(eccentricity, t1=2 * math.pi, dt=2 * math.pi / 20, dtype=jnp.float64)
    q, p = _solve(problem, diffrax.Dopri8(), rtol=1e-13, atol=1e-15)
    q_ref, p_ref = problem.reference(problem.ts)
    np.testing.assert_allclose(q, q_ref, atol=1e-10)
    np.testing.assert_allclose(p, p_ref, atol=1e-10)
    np.testing.assert_allclose(q_ref[-1], problem.y0[0], atol=1e-13)


# -- validation and jit ----------------------------------------------------------------------------
def test_argument_validation():
    for e in (1.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="eccentricity"):
            kepler(e)
    for n in (1, 0, 2.5, True):
        with pytest.raises(ValueError, match="n >= 2"):
            toda_lattice(n=n)
    with pytest.raises(ValueError, match="alpha"):
        toda_lattice(alpha=0.0)
    with pytest.raises(ValueError, match="q0"):
        toda_lattice(n=4, q0=(0.0, 1.0))
    with pytest.raises(ValueError, match="masses"):
        outer_solar_system(masses=(1.0, -1.0, 1.0, 1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="gravity"):
        outer_solar_system(gravity=-1.0)
    with pytest.raises(ValueError, match="q0"):
        outer_solar_system(masses=(1.0, 1e-3))
    with pytest.raises(ValueError, match="2 component"):
        henon_heiles(q0=(0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match="finite"):
        perturbed_pendulum(omega=float("inf"))
    with pytest.raises(ValueError, match="floating"):
        kepler(dtype=jnp.int32)


def test_jit_friendly_float32():
    for factory in FACTORIES:
        problem = factory(dtype=jnp.float32)
        vf = jax.jit(lambda term, y: term.vf(0.0, y, None))(problem.term, problem.y0)
        assert vf[0].dtype == vf[1].dtype == jnp.float32
        invariants = jax.jit(lambda inv, q, p: {k: fn(0.0, q, p, None) for k, fn in inv.items()})(
            dict(problem.invariants), *problem.y0
        )
        for value in invariants.values():
            assert value.dtype == jnp.float32
        hash(problem.term)


def test_outer_solar_system_float32_tsit5():
    problem = outer_solar_system(dtype=jnp.float32).with_span(20.0, dt=2.0)
    q, _ = _solve(problem, diffrax.Tsit5(), rtol=1e-6, atol=1e-9)
    assert q.dtype == np.float32
    q_ref, _ = problem.reference(problem.ts)
    np.testing.assert_allclose(q, q_ref, rtol=0, atol=1e-4)
