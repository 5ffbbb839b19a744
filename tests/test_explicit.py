"""The explicit symplectic solvers: StormerVerlet, Composition, BlanesMoan (diffrax_vi._explicit).

Orders are measured on the harmonic oscillator and on Kepler e = 0.5 (one orbit) from two or
three constant step sizes, each configuration compiled once (the step count is traced).
"""

from __future__ import annotations

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi._explicit import _splitting
from diffrax_vi._explicit._coefficients import composition_gammas, composition_schemes
from diffrax_vi._results import STEP_FAILURES

OSC = dvi.problems.harmonic_oscillator(t1=10.0)
KEPLER = dvi.problems.kepler(0.5, t1=2 * math.pi)


def stepper(solver, term, t0, t1, y0, args=None):
    """A jitted map `n ↦ y(t1)` by `n` constant steps of `solver.step` (compiled once)."""

    @jax.jit
    def run(n):
        h = (t1 - t0) / n
        state = solver.init(term, t0, t0 + h, y0, args)

        def body(i, carry):
            y, s = carry
            t = t0 + i * h
            y, _, _, s, _ = solver.step(term, t, t + h, y, args, s, False)
            return y, s

        return jax.lax.fori_loop(0, n, body, (y0, state))[0]

    return run


def errors(solver, problem, ns):
    run = stepper(solver, problem.term, problem.t0, problem.t1, problem.y0)
    qr, pr = problem.reference(np.array([problem.t1]))
    out = []
    for n in ns:
        q, p = run(n)
        out.append(np.linalg.norm(np.concatenate([np.asarray(q) - qr[-1],
                                                  np.asarray(p) - pr[-1]])))
    return np.array(out)


def slopes(ns, errs):
    ns = np.asarray(ns, float)
    return np.log(errs[:-1] / errs[1:]) / np.log(ns[1:] / ns[:-1])


# (solver, oscillator step counts over [0, 10], Kepler step counts over one orbit): sizes in
# each method's asymptotic regime, above double precision's round-off.
METHODS = {
    "stormer_verlet": (dvi.StormerVerlet(), (40, 80, 160), (800, 1600, 3200)),
    "c4_triple_jump": (dvi.Composition(4, "triple_jump"), (40, 80, 160), (200, 400, 800)),
    "c4_suzuki": (dvi.Composition(4, "suzuki"), (20, 40, 80), (50, 100, 200)),
    "c6_triple_jump": (dvi.Composition(6, "triple_jump"), (40, 80, 160), (200, 400, 800)),
    "c6_yoshida": (dvi.Composition(6, "yoshida"), (20, 40, 80), (100, 200, 400)),
    "c6_kahan_li": (dvi.Composition(6, "kahan_li"), (20, 40, 80), (100, 200, 400)),
    "c6_suzuki": (dvi.Composition(6, "suzuki"), (20, 40, 80), (100, 200, 400)),
    "c8_triple_jump": (dvi.Composition(8, "triple_jump"), (40, 80, 160), (200, 400, 800)),
    "c8_kahan_li": (dvi.Composition(8, "kahan_li"), (10, 20, 40), (50, 100, 200)),
    "blanes_moan_4": (dvi.BlanesMoan(4), (40, 80, 160), (400, 800, 1600)),
    "blanes_moan_6": (dvi.BlanesMoan(6), (10, 20, 40), (100, 200)),
}


@pytest.mark.parametrize("name", sorted(METHODS))
def test_measured_order(name):
    solver, n_osc, n_kepler = METHODS[name]
    order = solver.order(None)
    for problem, ns in ((OSC, n_osc), (KEPLER, n_kepler)):
        errs = errors(solver, problem, ns)
        assert np.all(errs < 1e-2) and np.all(errs > 1e-13), (problem.name, errs)
        assert np.all(np.abs(slopes(ns, errs) - order) < 0.1), (problem.name, errs)


def test_composition_fractions_meet_the_order_conditions():
    for order in (2, 4, 6, 8):
        for scheme in composition_schemes(order):
            g = np.array(composition_gammas(order, scheme))
            assert math.fsum(g) == pytest.approx(1, abs=1e-15)
            np.testing.assert_array_equal(g, g[::-1])
            for k in range(3, order, 2):  # Σ γ^k = 0 for odd k below the order
                assert abs(np.sum(g**k)) < 1e-12, (order, scheme, k)
    with pytest.raises(ValueError, match="unknown composition scheme 'nope'"):
        composition_gammas(4, "nope")
    with pytest.raises(ValueError, match="no set of order 4"):
        composition_gammas(4, "kahan_li")
    with pytest.raises(ValueError, match="order must be 4, 6 or 8"):
        dvi.Composition(5)
    with pytest.raises(ValueError, match="no scheme 'kahan_li' of order 4"):
        dvi.Composition(4, "kahan_li")
    with pytest.raises(ValueError, match="BlanesMoan: order must be 4 or 6"):
        dvi.BlanesMoan(8)
    with pytest.raises(ValueError, match="kick_iterations must be a positive int"):
        dvi.StormerVerlet(kick_iterations=0)


def _solve(solver, problem, n, y0=None, **kwargs):
    # Times as arrays: `diffeqsolve` compiles once for all their values.
    t0, t1 = jnp.asarray(problem.t0), jnp.asarray(problem.t1)
    return diffrax.diffeqsolve(problem.term, solver, t0, t1, (t1 - t0) / n,
                               problem.y0 if y0 is None else y0, **kwargs)


def test_diffeqsolve_takes_the_same_steps_and_dense_output_is_hermite():
    solver = dvi.Composition(6, "kahan_li")
    run = stepper(solver, KEPLER.term, KEPLER.t0, KEPLER.t1, KEPLER.y0)
    ts = np.linspace(KEPLER.t0, KEPLER.t1, 37)
    sol = _solve(solver, KEPLER, 200, saveat=diffrax.SaveAt(t1=True, ts=ts, dense=True))
    q, p = run(200)
    # The same steps, up to the rounding of the step ends (diffrax forms them its own way).
    np.testing.assert_allclose(sol.ys[0][-1], q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(sol.ys[1][-1], p, rtol=0, atol=1e-13)
    # Between the step ends the cubic Hermite interpolation of (q, p): fourth order in h.
    qr, pr = KEPLER.reference(ts)
    err = np.max(np.abs(np.asarray(sol.ys[0][:-1]) - qr))
    assert 1e-9 < err < 1e-5
    np.testing.assert_allclose(sol.evaluate(ts[5])[0], sol.ys[0][5], atol=1e-15)


def test_backward_integration_returns_to_the_start():
    solver = dvi.BlanesMoan(6)
    fwd = _solve(solver, KEPLER, 300)
    y1 = (fwd.ys[0][-1], fwd.ys[1][-1])
    t0, t1 = jnp.asarray(KEPLER.t0), jnp.asarray(KEPLER.t1)
    back = diffrax.diffeqsolve(KEPLER.term, solver, t1, t0, (t0 - t1) / 300, y1)
    for a, b in zip((back.ys[0][-1], back.ys[1][-1]), KEPLER.y0, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_grad_through_the_solve_matches_finite_differences():
    solver = dvi.Composition(4)
    problem = dvi.problems.kepler(0.5, t1=2.0)

    def loss(x):
        q0 = problem.y0[0] * x
        sol = _solve(solver, problem, 32, y0=(q0, problem.y0[1]))
        return jnp.sum(sol.ys[0][-1] ** 2) + jnp.sum(sol.ys[1][-1])

    x0, d = 1.0, 1e-3
    grad = jax.jit(jax.grad(loss))(x0)
    f = jax.jit(loss)

    def central(d):
        return (f(x0 + d) - f(x0 - d)) / (2 * d)

    fd = (4 * central(d / 2) - central(d)) / 3  # Richardson: truncation O(d⁴)
    assert abs(grad - fd) < 1e-7, (grad, fd)


def test_vmap_equals_the_loop():
    solver = dvi.Composition(8, "kahan_li")
    scale = jnp.linspace(0.9, 1.1, 5)

    # The step is an argument, as in a solve whose step is chosen at run time: with it a
    # compile-time constant XLA folds it differently into the batched and the single program.
    dt = jnp.asarray((KEPLER.t1 - KEPLER.t0) / 100)

    @jax.jit
    def final(s, dt):
        sol = diffrax.diffeqsolve(KEPLER.term, solver, KEPLER.t0, KEPLER.t1, dt,
                                  (KEPLER.y0[0] * s, KEPLER.y0[1]))
        return sol.ys[0][-1], sol.ys[1][-1]

    batched = jax.vmap(final, in_axes=(0, None))(scale, dt)
    for i, s in enumerate(scale):
        one = final(s, dt)
        for a, b in zip(one, batched, strict=True):
            assert np.max(np.abs(np.asarray(a) - np.asarray(b[i]))) <= 1e-15


@pytest.mark.parametrize("dtype", [jnp.float32, pytest.param(jnp.float16, marks=pytest.mark.slow)])
def test_low_precision_stays_in_its_dtype(dtype):
    problem = dvi.problems.kepler(0.5, t1=2.0, dtype=dtype)
    solver = dvi.Composition(4)
    ts = jnp.linspace(0.0, 2.0, 5, dtype=dtype)
    sol = diffrax.diffeqsolve(problem.term, solver, jnp.asarray(0.0, dtype),
                              jnp.asarray(2.0, dtype), jnp.asarray(0.05, dtype), problem.y0,
                              saveat=diffrax.SaveAt(ts=ts, solver_state=True))
    for leaf in jax.tree_util.tree_leaves((sol.ys, sol.solver_state)):
        assert leaf.dtype == dtype
    qr, _ = problem.reference(np.asarray(ts, np.float64))
    bound = 1e-4 if dtype == jnp.float32 else 5e-2
    assert np.max(np.abs(np.asarray(sol.ys[0], np.float64) - qr)) < bound


def test_compensated_summation_lowers_the_roundoff_of_long_runs():
    """A float32 state against float64 with the same method and step (a power of two, float64
    times): the difference is the float32 run's round-off."""
    n = 100_000
    span = n * 2.0**-9
    wide = dvi.problems.harmonic_oscillator(t1=span)
    narrow = dvi.problems.harmonic_oscillator(t1=span, dtype=jnp.float32)
    exact = stepper(dvi.StormerVerlet(), wide.term, 0.0, span, wide.y0)(n)
    drift = {}
    for compensated in (False, True):
        solver = dvi.StormerVerlet(compensated=compensated)
        q, _ = stepper(solver, narrow.term, 0.0, span, narrow.y0)(n)
        assert q.dtype == jnp.float32
        drift[compensated] = float(np.max(np.abs(np.asarray(q, np.float64) - exact[0])))
    assert drift[True] < drift[False] / 100, drift


def _mass_lagrangian(t, q, v, args):
    mass = jnp.array([[2.0, 0.3], [0.3, 1.0]]) if args is None else args
    stiffness = jnp.array([1.0, 2.0]) * (1 + 0.3 * jnp.sin(t))
    return 0.5 * v @ mass @ v - 0.5 * jnp.sum(stiffness * q**2) - 0.1 * q[0] ** 3 * q[1]


def _reference(term, y0, t1, args=None):
    sol = diffrax.diffeqsolve(term, diffrax.Dopri8(), 0.0, t1, 0.01, y0, args,
                              stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
                              max_steps=100_000)
    return np.concatenate([np.asarray(sol.ys[0][-1]), np.asarray(sol.ys[1][-1])])


def _order_against(solver, term, y0, t1, ns, args=None):
    ref = _reference(term, y0, t1, args)
    run = stepper(solver, term, 0.0, t1, y0, args)
    errs = np.array([np.max(np.abs(np.concatenate(run(n)) - ref)) for n in ns])
    return slopes(ns, errs), errs


def test_time_dependent_potential_and_constant_mass_matrix():
    term = dvi.LagrangianTerm(_mass_lagrangian)
    y0 = (jnp.array([0.4, -0.2]), jnp.array([0.1, 0.3]))
    s, errs = _order_against(dvi.Composition(4), term, y0, 4.0, (20, 40))
    assert abs(s[0] - 4) < 0.1, errs
    # The same matrix read from `args` (inverted at every step) gives the same steps.
    mass = jnp.array([[2.0, 0.3], [0.3, 1.0]])
    a = stepper(dvi.Composition(4), term, 0.0, 4.0, y0)(40)
    b = stepper(dvi.Composition(4), term, 0.0, 4.0, y0, mass)(40)
    np.testing.assert_allclose(np.concatenate(a), np.concatenate(b), atol=1e-14)


def _oscillator(t, q, v, args):
    return 0.5 * v @ v - 0.5 * q @ q


def test_position_force_keeps_the_order():
    """A non-gradient force of the position (a swirl) keeps an RKN splitting's order."""
    term = dvi.LagrangianTerm(_oscillator, force=lambda t, q, v, a: 0.3 * jnp.array([-q[1], q[0]]))
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.0, 0.8]))
    s, errs = _order_against(dvi.BlanesMoan(4), term, y0, 5.0, (20, 40))
    assert abs(s[0] - 4) < 0.1, errs


def _damping(t, q, v, args):
    return -0.2 * v - 0.1 * v**3 * (1 + q**2)


def test_velocity_force_is_kicked_implicitly_and_keeps_the_order():
    term = dvi.LagrangianTerm(_oscillator, force=_damping)
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.0, 0.8]))
    for solver, order, ns in ((dvi.StormerVerlet(), 2, (100, 200)),
                              (dvi.Composition(4), 4, (20, 40))):
        s, errs = _order_against(solver, term, y0, 5.0, ns)
        assert abs(s[0] - order) < 0.1, (solver, errs)
    with pytest.raises(ValueError, match="BlanesMoan: the term's non-conservative force reads"):
        stepper(dvi.BlanesMoan(4), term, 0.0, 1.0, y0)(4)
    # One Newton iteration cannot converge a nonlinear kick: a failed step, not a silent one.
    sol = diffrax.diffeqsolve(term, dvi.StormerVerlet(kick_iterations=1), 0.0, 1.0, 0.1, y0,
                              throw=False)
    assert sol.result == STEP_FAILURES["vi_step_max_iterations"]


@pytest.mark.parametrize(
    "lagrangian, why",
    [
        (lambda t, q, v, a: 0.5 * (1 + q[0] ** 2) * v @ v - 0.5 * q @ q, "kinetic matrix"),
        (lambda t, q, v, a: 0.5 * v @ v + q[0] * v[1] - 0.5 * q @ q, "momentum offset"),
    ],
)
def test_non_separable_lagrangian_is_refused_by_name(lagrangian, why):
    term = dvi.LagrangianTerm(lagrangian)
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.0, 0.8]))
    for solver in (dvi.StormerVerlet(), dvi.Composition(6), dvi.BlanesMoan(4)):
        name = type(solver).__name__
        with pytest.raises(ValueError, match=f"{name} needs a separable Lagrangian") as info:
            diffrax.diffeqsolve(term, solver, 0.0, 1.0, 0.1, y0)
        assert why in str(info.value) and "diffrax_vi.CGVI" in str(info.value)


@pytest.mark.parametrize("solver", [dvi.StormerVerlet(), dvi.Composition(6), dvi.BlanesMoan(4)],
                         ids=["stormer_verlet", "composition", "blanes_moan"])
def test_a_step_of_the_wrong_sign_is_refused(solver):
    name = type(solver).__name__
    state = solver.init(KEPLER.term, 1.0, 0.9, KEPLER.y0, None)
    with pytest.raises(ValueError, match=f"{name}: a step must go forward") as info:
        solver.step(KEPLER.term, 1.0, 0.9, KEPLER.y0, None, state, False)
    assert "t1 < t0 and a negative dt0" in str(info.value)
    # a traced step of the wrong sign: a runtime error with the same message
    step = jax.jit(lambda t1: solver.step(KEPLER.term, 1.0, t1, KEPLER.y0, None, state,
                                          False)[0])
    with pytest.raises(Exception, match=f"{name}: a step must go forward"):
        jax.block_until_ready(step(jnp.asarray(0.9)))
    with pytest.raises(Exception, match=r"Must have \(t1 - t0\) \* dt0 >= 0"):
        diffrax.diffeqsolve(KEPLER.term, solver, 0.0, 1.0, -0.1, KEPLER.y0)


def test_pid_controller_uses_the_step_doubling_estimate():
    solver = dvi.Composition(6, "kahan_li")
    sol = _solve(solver, KEPLER, 60,
                 stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
    qr, pr = KEPLER.reference(np.array([KEPLER.t1]))
    err = max(np.max(np.abs(sol.ys[0][-1] - qr[-1])), np.max(np.abs(sol.ys[1][-1] - pr[-1])))
    assert err < 1e-6
    assert 20 < int(sol.stats["num_accepted_steps"]) < 400
    # The estimate against the true local error of one step.
    h = 0.2

    @jax.jit
    def one_step(y0):
        state = solver.init(KEPLER.term, 0.0, h, y0, None)
        return solver.step(KEPLER.term, 0.0, h, y0, None, state, False)[:2]

    y1, y_err = one_step(KEPLER.y0)
    q_exact, p_exact = KEPLER.reference(np.array([h]))
    true = np.concatenate([y1[0] - q_exact[-1], y1[1] - p_exact[-1]])
    estimate = np.concatenate(y_err)
    assert 0.5 < np.max(np.abs(estimate)) / np.max(np.abs(true)) < 2


def test_stages_in_a_scan_match_the_unrolled_stages(monkeypatch):
    solver = dvi.Composition(6, "triple_jump")
    unrolled = stepper(solver, KEPLER.term, KEPLER.t0, KEPLER.t1, KEPLER.y0)(50)
    monkeypatch.setattr(_splitting, "UNROLL_LIMIT", 0)
    scanned = stepper(solver, KEPLER.term, KEPLER.t0, KEPLER.t1, KEPLER.y0)(50)
    np.testing.assert_allclose(np.concatenate(scanned), np.concatenate(unrolled), atol=1e-13)


def test_constraints_go_to_rattle_or_are_refused():
    term = dvi.LagrangianTerm(lambda t, q, v, a: 0.5 * v @ v - q[1],
                              constraint=lambda t, q, a: jnp.array([q @ q - 1.0]))
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.0, 0.0]))
    with pytest.raises(ValueError, match="BlanesMoan cannot take a term with holonomic"):
        diffrax.diffeqsolve(term, dvi.BlanesMoan(4), 0.0, 1.0, 0.1, y0)
    # Composition's sub-steps are RATTLE steps: the end state is on the circle.
    sol = diffrax.diffeqsolve(term, dvi.Composition(4), 0.0, 1.0, 0.05, y0)
    assert abs(float(jnp.sum(sol.ys[0][-1] ** 2)) - 1) < 1e-12


# slow, not long: each run takes 0.5-2 s after its compilation (2026-12-02)
@pytest.mark.slow
@pytest.mark.parametrize("run", range(6))
def test_energy_error_stays_bounded_over_a_million_kepler_steps(run):
    from benchmarks.explicit_methods import ENERGY_RUNS, energy_growth

    solver, h = ENERGY_RUNS[run]
    first, last = energy_growth(solver, h, 1_000_000)
    assert last <= 3 * first, (first, last)
