"""The harder problems: a slowly modulated (time-dependent) oscillator, a charged particle in a
non-uniform magnetic field and the stiff Fermi–Pasta–Ulam chain. Their stored references against
an independent integration, their invariants, a cGVI solve at its order, validation, dtypes."""

import jax

jax.config.update("jax_enable_x64", True)

import math  # noqa: E402

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi.problems import (  # noqa: E402
    charged_particle,
    fermi_pasta_ulam,
    modulated_oscillator,
)
from tests.helpers import check_stored_data  # noqa: E402

FACTORIES = [modulated_oscillator, charged_particle, fermi_pasta_ulam]
# max-norm accuracy of the stored flows over (q, p): what the generator verified, with a margin
STORED_ACCURACY = {
    "modulated_oscillator": 1e-14,
    "charged_particle": 1e-14,
    "fermi_pasta_ulam": 1e-13,  # the stiff momenta carry the rounding of ω² x₁ (ω = 50)
}
# spans of the independent DOP853 check (short: DOP853 at rtol 1e-13 costs a jitted JAX call
# per stage) and the agreement claimed, relative to the largest |q| or |p|
DOP853_SPANS = {"modulated_oscillator": 40.0, "charged_particle": 5.0, "fermi_pasta_ulam": 2.0}
DOP853_AGREEMENT = 1e-11


def _invariants_along(problem, ts, q, p):
    ts = jnp.asarray(ts)
    return {
        name: np.asarray(jax.vmap(fn, in_axes=(0, 0, 0, None))(ts, q, p, problem.args))
        for name, fn in problem.invariants.items()
    }


def _dop853_from_term(problem, tau):
    """Hamilton's equations from the problem's JAX term (not the NumPy field of its stored
    flow), integrated by scipy's DOP853 at rtol 1e-13 from `t0` to `t0 + tau`."""
    from scipy.integrate import solve_ivp

    d = problem.dim
    vf = jax.jit(lambda t, y: jnp.concatenate(problem.term.vf(t, (y[:d], y[d:]), None)))
    y0 = np.concatenate([np.asarray(x) for x in problem.y0])
    sol = solve_ivp(
        lambda t, y: np.asarray(vf(t, jnp.asarray(y))),
        (problem.t0, problem.t0 + tau[-1]),
        y0,
        method="DOP853",
        t_eval=problem.t0 + tau,
        rtol=1e-13,
        atol=1e-15,
    )
    assert sol.success
    return sol.y.T[:, :d], sol.y.T[:, d:]


# -- stored references ---------------------------------------------------------------------------
@pytest.mark.parametrize("factory", FACTORIES)
def test_stored_data_present_and_small(factory):
    problem = factory(dtype=jnp.float64)
    check_stored_data(problem, STORED_ACCURACY[problem.name], max_bytes=200_000)


@pytest.mark.parametrize("factory", FACTORIES)
def test_stored_reference_matches_dop853_of_the_term(factory):
    pytest.importorskip("scipy")
    problem = factory(dtype=jnp.float64)
    tau = np.linspace(0.0, DOP853_SPANS[problem.name], 11)[1:]
    q, p = problem.reference(problem.t0 + tau)
    q_dop, p_dop = _dop853_from_term(problem, tau)
    np.testing.assert_allclose(q, q_dop, rtol=0, atol=DOP853_AGREEMENT * np.abs(q).max())
    np.testing.assert_allclose(p, p_dop, rtol=0, atol=DOP853_AGREEMENT * np.abs(p).max())


@pytest.mark.parametrize("factory", [charged_particle, fermi_pasta_ulam])
def test_stored_reference_conserves_invariants(factory):
    problem = factory(dtype=jnp.float64)
    ts = np.linspace(problem.t0, problem.t1, 401)
    q, p = problem.reference(ts)
    invariants = _invariants_along(problem, ts, q, p)
    exact = {"energy", "angular_momentum"}  # the oscillatory energies are adiabatic only
    for name in exact & set(invariants):
        values = invariants[name]
        assert np.max(np.abs(values - values[0])) / np.abs(values[0]) < 1e-13, name
    if problem.name == "fermi_pasta_ulam":
        omega = problem.params["omega"]
        total = invariants["oscillatory_energy"]
        np.testing.assert_allclose(total[0], 1.0, rtol=1e-15)
        # adiabatic: I = I(0) + O(1/ω) (measured 0.062 for ω = 50), while the Iⱼ exchange energy
        assert np.max(np.abs(total - total[0])) < 5 / omega
        each = invariants["oscillatory_energies"]
        np.testing.assert_allclose(each.sum(axis=1), total, rtol=1e-13)
        assert each[:, 2].max() > 0.5


def test_modulated_oscillator_adiabatic_invariant_and_energy_identity():
    problem = modulated_oscillator(dtype=jnp.float64)
    omega0, epsilon, nu = (problem.params[k] for k in ("omega0", "epsilon", "nu"))
    ts = np.linspace(problem.t0, problem.t1, 401)
    q, p = problem.reference(ts)
    j = _invariants_along(problem, ts, q, p)["adiabatic_invariant"]
    energy = np.asarray(jax.vmap(problem.energy)(jnp.asarray(ts), q, p))
    # the energy swings with ω (by a factor 3 here) while J = H/ω varies by O(εν/ω₀) only
    assert energy.max() / energy.min() > 2.5
    assert np.max(np.abs(j / j[0] - 1)) < 2 * epsilon * nu / omega0
    # dH/dt = ∂H/∂t along the reference: the flow is that of the time-dependent equations
    h = 1e-3
    times = ts[10:-10:20]
    up, down = problem.reference(times + h), problem.reference(times - h)
    up2, down2 = problem.reference(times + 2 * h), problem.reference(times - 2 * h)
    e = lambda t, qp: np.asarray(jax.vmap(problem.energy)(jnp.asarray(t), *qp))  # noqa: E731
    derivative = (
        8 * (e(times + h, up) - e(times - h, down))
        - (e(times + 2 * h, up2) - e(times - 2 * h, down2))
    ) / (12 * h)
    q_mid, p_mid = problem.reference(times)
    partial = jax.vmap(jax.grad(problem.energy))(jnp.asarray(times), q_mid, p_mid)
    np.testing.assert_allclose(derivative, partial, rtol=0, atol=1e-9)


def test_modulated_oscillator_reference_depends_on_the_start_time():
    pytest.importorskip("scipy")
    problem = modulated_oscillator(dtype=jnp.float64)
    shifted = modulated_oscillator(t0=5.0, t1=25.0, dtype=jnp.float64)
    assert shifted.reference_flow.data is None  # stored for t0 = 0 only
    tau = np.array([3.0, 10.0])
    q_shift, p_shift = shifted.reference(5.0 + tau)
    assert np.max(np.abs(q_shift - problem.reference(tau)[0])) > 1e-3
    q_dop, p_dop = _dop853_from_term(shifted, tau)
    np.testing.assert_allclose(q_shift, q_dop, atol=1e-11)
    np.testing.assert_allclose(p_shift, p_dop, atol=1e-11)
    # outside the stored span, and the non-autonomous field in scipy's convention
    flow = problem.reference_flow
    assert flow.time_dependent and flow.y0.shape == (3,)
    q_out, _ = problem.reference([-1.0, 201.0])
    q_in, _ = problem.reference([0.0, 200.0])
    assert np.all(np.isfinite(q_out)) and np.max(np.abs(q_out - q_in)) > 1e-3
    y = np.array([0.3, -0.2])
    omega = 1.0 * (1 + 0.5 * math.sin(0.1 * 7.0))
    np.testing.assert_allclose(flow.vector_field(7.0, y), [-0.2, -(omega**2) * 0.3], rtol=1e-15)
    with pytest.raises(ValueError, match="time-dependent"):
        flow.rhs(y)


# -- maps and invariants ---------------------------------------------------------------------------
def test_charged_particle_momentum_is_not_the_velocity():
    problem = charged_particle(dtype=jnp.float64)
    b0, kappa = problem.params["b0"], problem.params["kappa"]
    term = problem.term
    q0, p0 = problem.y0
    np.testing.assert_allclose(term.velocity(0.0, q0, p0, None), [0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(p0, [0.0, 1.0 + b0 * (0.5 + 0.25 * kappa)], rtol=1e-15)
    numerical = dvi.LagrangianTerm(term.lagrangian)  # Newton's inverse of ∂L/∂v
    rng = np.random.default_rng(0)
    for _ in range(3):
        q, v = jnp.asarray(rng.normal(size=2)), jnp.asarray(rng.normal(size=2))
        f = b0 * (0.5 + 0.25 * kappa * float(q @ q))
        p = term.momentum(0.0, q, v, None)
        np.testing.assert_allclose(p, v + f * jnp.array([-q[1], q[0]]), rtol=1e-14)
        np.testing.assert_allclose(numerical.velocity(0.0, q, p, None), v, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(term.energy(0.0, q, p, None), 0.5 * float(v @ v), rtol=1e-13)
        # the Lorentz force: d(p − A)/dt = (v_y, −v_x) B_z, B_z = B₀ (1 + κ r²)
        _, dp = term.vf(0.0, (q, p), None)
        grad_a = jax.jacfwd(lambda x: term.lagrangian.potential(x))(q)
        dv = dp - grad_a @ v
        bz = b0 * (1 + kappa * float(q @ q))
        np.testing.assert_allclose(dv, bz * jnp.array([v[1], -v[0]]), rtol=1e-12, atol=1e-14)


def test_initial_invariants():
    fpu = fermi_pasta_ulam(dtype=jnp.float64)
    q0, p0 = fpu.y0
    np.testing.assert_array_equal(q0, [1.0, 0.0, 0.0, 0.02, 0.0, 0.0])
    np.testing.assert_array_equal(p0, [1.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    quartic = 0.25 * ((1 - 0.02) ** 4 + (1 + 0.02) ** 4)
    np.testing.assert_allclose(fpu.energy(0.0, q0, p0), 1.0 + 0.5 + quartic, rtol=1e-15)
    invariants = {k: fn(0.0, q0, p0, None) for k, fn in fpu.invariants.items()}
    np.testing.assert_allclose(invariants["oscillatory_energies"], [1.0, 0.0, 0.0], rtol=1e-15)
    mo = modulated_oscillator(omega0=2.0, epsilon=0.3, nu=0.05, q0=0.5, p0=0.4, t0=3.0)
    omega = 2.0 * (1 + 0.3 * math.sin(0.05 * 3.0))
    h0 = 0.5 * 0.4**2 + 0.5 * omega**2 * 0.5**2
    np.testing.assert_allclose(mo.energy(3.0, *mo.y0), h0, rtol=1e-14)
    j0 = mo.invariants["adiabatic_invariant"](3.0, *mo.y0, None)
    np.testing.assert_allclose(j0, h0 / omega, rtol=1e-14)
    cp = charged_particle(b0=2.0, kappa=0.5, q0=(0.0, 2.0), v0=(0.5, 0.0), dtype=jnp.float64)
    invariants = {k: fn(0.0, *cp.y0, None) for k, fn in cp.invariants.items()}
    np.testing.assert_allclose(invariants["energy"], 0.125, rtol=1e-15)
    # x v_y − y v_x + r² B₀ (1/2 + κ r²/4) = −1 + 4·2·1 = 7
    np.testing.assert_allclose(invariants["angular_momentum"], 7.0, rtol=1e-15)


# -- a cGVI of order 12 ----------------------------------------------------------------------------
# (problem, span, step): the steps are moderate (about 1/6, 1/7 and 1/3 of the shortest period:
# the modulated oscillator at ω ≤ 1.5, the gyration at B ≈ 9, the stiff springs at ω = 50)
CGVI_CASES = [
    (modulated_oscillator, 24.0, 2.0),
    (charged_particle, 4.0, 0.2),
    (fermi_pasta_ulam, 0.8, 0.04),
]


@pytest.mark.parametrize(("factory", "t1", "dt"), CGVI_CASES)
def test_cgvi6_converges_to_the_reference_at_its_order(factory, t1, dt):
    """`CGVI(6)` has order 12: halving the step divides the error at `t1` by about 4096; we
    claim a factor above 2⁹ (three orders of slack for a pre-asymptotic step), and that the
    finer solve lands within 1e-7 (relative) of the reference: its map depends on the time
    where the problem does."""
    problem = factory(dtype=jnp.float64).with_span(t1, dt=dt)

    @eqx.filter_jit
    def end(y0, step):
        sol = diffrax.diffeqsolve(
            problem.term, dvi.CGVI(6), problem.t0, problem.t1, step, y0,
            saveat=diffrax.SaveAt(t1=True), max_steps=64,
        )
        return sol.ys, sol.result

    q_ref, p_ref = problem.reference([problem.t1])
    scale = max(np.abs(q_ref).max(), np.abs(p_ref).max())
    errors = []
    for step in (dt, dt / 2):
        (q, p), result = end(problem.y0, jnp.asarray(step))
        assert result == diffrax.RESULTS.successful
        errors.append(max(np.abs(q - q_ref).max(), np.abs(p - p_ref).max()) / scale)
    assert errors[1] < 1e-7
    assert errors[0] / errors[1] > 2**9, errors


# -- validation, dtypes ----------------------------------------------------------------------------
def test_argument_validation():
    for kwargs, name in [
        ({"omega0": 0.0}, "omega0"),
        ({"omega0": float("nan")}, "omega0"),
        ({"epsilon": 1.0}, "epsilon"),
        ({"epsilon": -0.1}, "epsilon"),
        ({"nu": -1.0}, "nu"),
        ({"q0": (1.0, 2.0)}, "q0"),
    ]:
        with pytest.raises(ValueError, match=name):
            modulated_oscillator(**kwargs)
    for kwargs, name in [
        ({"b0": 0.0}, "b0"),
        ({"b0": float("inf")}, "b0"),
        ({"kappa": -1.0}, "kappa"),
        ({"q0": (1.0,)}, "q0"),
        ({"v0": (0.0, 1.0, 2.0)}, "v0"),
    ]:
        with pytest.raises(ValueError, match=name):
            charged_particle(**kwargs)
    for kwargs, name in [
        ({"m": 0}, "m"),
        ({"m": 2.5}, "m"),
        ({"m": True}, "m"),
        ({"omega": -50.0}, "omega"),
        ({"q0": (1.0, 0.0)}, "q0"),
        ({"p0": np.zeros(5)}, "p0"),
    ]:
        with pytest.raises(ValueError, match=name):
            fermi_pasta_ulam(**kwargs)
    with pytest.raises(ValueError, match="floating"):
        fermi_pasta_ulam(dtype=jnp.int32)


@pytest.mark.parametrize("factory", FACTORIES)
def test_float32_state_maps_and_invariants(factory):
    problem = factory(dtype=jnp.float32)
    q0, p0 = problem.y0
    assert q0.dtype == p0.dtype == jnp.float32
    assert q0.shape == p0.shape == (problem.dim,)
    vf = jax.jit(lambda term, y: term.vf(1.5, y, None))(problem.term, problem.y0)
    assert vf[0].dtype == vf[1].dtype == jnp.float32
    assert problem.energy(problem.t0, q0, p0).dtype == jnp.float32
    for fn in problem.invariants.values():
        assert jnp.result_type(fn(problem.t0, q0, p0, None)) == jnp.float32
    problem.n_steps  # noqa: B018 - dt divides the default span
    hash(problem.term)


def test_other_sizes_use_scipy():
    pytest.importorskip("scipy")
    problem = fermi_pasta_ulam(m=2, omega=20.0, t1=1.0, dtype=jnp.float64)
    assert problem.dim == 4 and problem.reference_flow.data is None
    ts = np.linspace(0.0, 1.0, 5)
    q, p = problem.reference(ts)
    energy = _invariants_along(problem, ts, q, p)["energy"]
    np.testing.assert_allclose(energy, energy[0], rtol=1e-12)


def test_the_harness_scipy_field_knows_the_time_of_a_time_dependent_problem():
    """The benchmark harness hands scipy Hamilton's equations at the absolute time: for the
    modulated oscillator they differ from the autonomous field at another time."""
    from diffrax_vi.bench.harness import numpy_rhs

    problem = modulated_oscillator()
    fun, source = numpy_rhs(problem)
    assert source == "numpy"
    y = np.concatenate([np.asarray(x, np.float64) for x in problem.y0])
    for t in (0.0, 3.0, 17.5):
        v, f = problem.term.vf(t, problem.y0, problem.args)
        np.testing.assert_allclose(fun(t, y), np.concatenate([v, f]), rtol=1e-15, atol=1e-15)
    assert not np.allclose(fun(0.0, y), fun(3.0, y))
