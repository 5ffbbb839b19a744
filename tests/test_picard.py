"""The Jacobian-free iteration of the projected step (`diffrax_vi._step.jacobian_free`)."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._kinetic_structure import kinetic_structure
from diffrax_vi._root_finder.chord import ChordIteration
from diffrax_vi._root_finder.jacobian_free import JacobianFreeIteration
from diffrax_vi._root_finder.solve import one_step_solve
from diffrax_vi._root_finder.step_hints import StepHints, step_options
from diffrax_vi._step.jacobian_free import engine_start, engine_update, start_at_rest

jax.config.update("jax_enable_x64", True)

CHORD = ChordIteration(ftol=0.0, predict=True, picard=False, restart=True)
ENGINE = ChordIteration(ftol=0.0, predict=True, picard=True)
FALLBACK = ChordIteration(ftol=0.0, predict=True, picard=True, picard_fallback=True)

MASS = jnp.array([[2.0, 0.3], [0.3, 1.0]])


def _mass_spring(t, q, v, args):
    return 0.5 * v @ MASS @ v - 0.5 * q @ q - 0.1 * q[0] ** 4


CASES = {
    # problem, step, steps
    "kepler": (lambda: problems.kepler(eccentricity=0.5), 2 * np.pi / 100, 60),
    "charged_particle": (problems.charged_particle, 0.05, 40),
    "mass_spring": (None, 0.2, 40),  # a constant mass matrix that is not the identity
}


def _problem(name):
    if name == "mass_spring":
        term = dvi.LagrangianTerm(_mass_spring)
        return term, (jnp.array([0.5, -0.2]), jnp.array([0.1, 0.3])), None
    problem = CASES[name][0]()
    return problem.term, problem.y0, problem.args


def _solve(solver, name, n=None, y0=None, saveat=None):
    term, y, args = _problem(name)
    _, h, steps = CASES[name]
    n = steps if n is None else n

    @eqx.filter_jit
    def go(y):
        return diffrax.diffeqsolve(
            term, solver, 0.0, n * h, h, y, args=args, max_steps=n,
            saveat=saveat or diffrax.SaveAt(t1=True, solver_state=True), throw=False,
        )

    return go(y if y0 is None else y0)


def _engine(solver, term, y0, args, h=0.1):
    ctx = solver.step_context(term, 0.0, h, y0, args)
    return solver.seeder.engine(ctx)


def test_structure_is_read_from_the_lagrangian():
    kepler = problems.kepler()
    q = jnp.ones(2)
    s = kinetic_structure(kepler.term, jnp.zeros(()), q, kepler.args)
    assert s.mass_constant and not s.offset_moves and not s.force_reads_velocity
    np.testing.assert_array_equal(s.mass, np.eye(2))
    particle = problems.charged_particle()
    s = kinetic_structure(particle.term, jnp.zeros(()), particle.y0[0], particle.args)
    assert s.mass_constant and s.offset_moves and s.force_reads_velocity
    pendulum = problems.double_pendulum()
    s = kinetic_structure(pendulum.term, jnp.zeros(()), pendulum.y0[0], pendulum.args)
    assert not s.mass_constant
    # a mass that is a parameter: constant, but known only when the step runs
    term = dvi.LagrangianTerm(lambda t, q, v, m: 0.5 * m * v @ v - 0.5 * q @ q)
    s = kinetic_structure(term, jnp.zeros(()), q, jnp.asarray(2.0))
    assert s.mass_constant and s.mass is None


def test_the_engine_is_chosen_only_where_it_applies():
    kepler = problems.kepler()
    assert _engine(dvi.CGVI(6, root_finder=ENGINE), kepler.term, kepler.y0, kepler.args) is not None
    assert _engine(dvi.CGVI(6, root_finder=CHORD), kepler.term, kepler.y0, kepler.args) is None
    # the defaults take it where it fits, decided when the step is traced
    assert _engine(dvi.CGVI(6), kepler.term, kepler.y0, kepler.args) is not None
    network = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10))
    assert _engine(network, kepler.term, kepler.y0, kepler.args) is not None
    # and the chord or Newton iteration where it does not (a kinetic matrix that moves)
    pendulum = problems.double_pendulum()
    for solver in (dvi.CGVI(6, root_finder=ENGINE), dvi.CGVI(6), network):
        assert _engine(solver, pendulum.term, pendulum.y0, pendulum.args) is None
    # an explicit root finder without `picard` is respected
    plain_network = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10),
                                  root_finder=dvi.RoundoffNewton(confirm=False))
    assert _engine(plain_network, kepler.term, kepler.y0, kepler.args) is None


# the mass-spring case here; each case's engine step: test_its_step_is_a_root_of_the_step_equations
@pytest.mark.parametrize("name", [
    "mass_spring",
    *(pytest.param(n, marks=pytest.mark.slow) for n in ("kepler", "charged_particle")),
])
def test_same_steps_as_the_chord_iteration(name):
    # Same equations, same root: the runs agree to round-off, and the engine took its own
    # path on every step (no restart through the chord iteration).
    fast = _solve(dvi.CGVI(6, root_finder=ENGINE), name)
    chord = _solve(dvi.CGVI(6, root_finder=CHORD), name)
    assert fast.result == diffrax.RESULTS.successful
    assert int(fast.solver_state.restarts) == 0
    for a, b in zip(fast.ys, chord.ys, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-13)


@pytest.mark.parametrize("name", list(CASES))
def test_its_step_is_a_root_of_the_step_equations(name):
    # The residual of the projected step's equations as the formulation writes them, at the
    # engine's unknowns from a start at rest, is at round-off.
    solver = dvi.CGVI(6, root_finder=ENGINE)
    term, y0, args = _problem(name)
    ctx = solver.step_context(term, 0.0, CASES[name][1], y0, args)
    engine = solver.seeder.engine(ctx)  # decided from the concrete context
    span = engine.span
    hints = StepHints(update=engine_update(engine), max_iterations=100)

    @eqx.filter_jit  # one program (op by op, the solve compiled some 90)
    def solve_and_residual(ctx):
        z, result, _, _ = one_step_solve(
            JacobianFreeIteration(), lambda z, a: solver.formulation.reduced_residual_and_forces(
                z, (a[0], span, None), fused=True),
            engine_start(engine, ctx, start_at_rest(ctx)), (ctx,), step_options(hints))
        return result, solver.formulation.reduced_residual(z, (ctx, span, None))

    result, (r, c) = solve_and_residual(ctx)
    assert result == optx.RESULTS.successful
    scale = 1 + max(float(jnp.max(jnp.abs(y0[0]))), float(jnp.max(jnp.abs(y0[1]))))
    assert max(float(jnp.max(jnp.abs(r))), float(jnp.max(jnp.abs(c)))) <= (
        64 * np.finfo(np.float64).eps * scale
    )


def test_gradients_match_finite_differences():
    term = dvi.LagrangianTerm(lambda t, q, v, k: 0.5 * v @ v - 0.5 * k * q @ q - 0.1 * q[0] ** 4)
    solver = dvi.CGVI(4, root_finder=ENGINE)
    assert _engine(solver, term, (jnp.ones(2), jnp.ones(2)), jnp.asarray(1.3)) is not None

    def final(k, q0):
        sol = diffrax.diffeqsolve(term, solver, 0.0, 3.0, 0.3, (q0, jnp.array([0.1, 0.0])),
                                  args=k, saveat=diffrax.SaveAt(t1=True))
        return sol.ys[0][-1, 0] + sol.ys[1][-1, 1]

    k, q0 = 1.3, jnp.array([0.5, 0.2])
    gk, gq = jax.grad(final, argnums=(0, 1))(k, q0)
    d = 1e-6
    fk = (final(k + d, q0) - final(k - d, q0)) / (2 * d)
    fq = [(final(k, q0.at[i].add(d)) - final(k, q0.at[i].add(-d))) / (2 * d) for i in range(2)]
    np.testing.assert_allclose(float(gk), float(fk), rtol=1e-7)
    np.testing.assert_allclose(np.asarray(gq), np.asarray(fq), rtol=1e-7, atol=1e-9)


def test_vmap_equals_the_loop():
    # (batched, the engine's products with constants run as one batched product instead of
    # a fused reduction: the members agree with their single runs to rounding)
    kepler = problems.kepler(eccentricity=0.5)
    q0s = jnp.stack([kepler.y0[0] * s for s in (1.0, 1.02, 0.97)])
    p0s = jnp.stack([kepler.y0[1] / np.sqrt(s) for s in (1.0, 1.02, 0.97)])
    solver = dvi.CGVI(6, root_finder=ENGINE)

    def one(q, p):
        sol = _solve(solver, "kepler", y0=(q, p), saveat=diffrax.SaveAt(t1=True))
        return sol.ys

    batched = jax.vmap(one)(q0s, p0s)
    for i in range(3):
        single = one(q0s[i], p0s[i])
        for a, b in zip(batched, single, strict=True):
            np.testing.assert_allclose(np.asarray(a[i]), np.asarray(b), rtol=1e-13, atol=1e-15)


def _stiff_quartic(solver, stiffness, controller=None, max_steps=10):
    term = dvi.LagrangianTerm(lambda t, q, v, k: 0.5 * v @ v - k * jnp.sum(q**4))
    return diffrax.diffeqsolve(term, solver, 0.0, 1.0, 0.1,
                               (jnp.array([1.0]), jnp.array([0.0])), args=stiffness,
                               max_steps=max_steps, throw=False,
                               stepsize_controller=controller or diffrax.ConstantStepSize(),
                               saveat=diffrax.SaveAt(t1=True, solver_state=True))


def test_a_step_it_cannot_contract_goes_to_newtons_iteration():
    # A stiff quartic spring at a long step: on some steps the Jacobian-free iteration does
    # not contract; with `picard_fallback` those steps are handed to Newton's iteration on
    # the same equations (a restart), and the run ends where the chord iteration alone ends
    # it. Stiffer still, Newton's iteration from that start fails too, and the run says so.
    fast = _stiff_quartic(dvi.CGVI(6, root_finder=FALLBACK), 110.0)
    chord = _stiff_quartic(dvi.CGVI(6, root_finder=CHORD), 110.0)
    assert fast.result == chord.result == diffrax.RESULTS.successful
    assert int(fast.solver_state.restarts) > 0
    np.testing.assert_allclose(np.asarray(fast.ys[0]), np.asarray(chord.ys[0]),
                               rtol=0, atol=1e-12)
    failed = _stiff_quartic(dvi.CGVI(6, root_finder=FALLBACK), 2500.0)
    assert failed.result != diffrax.RESULTS.successful


def test_without_the_fallback_a_step_it_cannot_contract_fails_and_is_retried():
    # The default: no Newton iteration inside the step. The step the iteration does not
    # contract on fails loudly at a constant step, and `RetryFailedSteps` recovers it in
    # smaller pieces: at least as accurate as the chord iteration's run at full steps,
    # against Dopri8 at rtol 1e-13.
    failed = _stiff_quartic(dvi.CGVI(6), 110.0)
    assert failed.result != diffrax.RESULTS.successful
    assert int(failed.solver_state.restarts) == 0
    retried = _stiff_quartic(dvi.CGVI(6), 110.0, dvi.RetryFailedSteps(), max_steps=100)
    chord = _stiff_quartic(dvi.CGVI(6, root_finder=CHORD), 110.0)
    assert retried.result == diffrax.RESULTS.successful
    term = dvi.LagrangianTerm(lambda t, q, v, k: 0.5 * v @ v - k * jnp.sum(q**4))
    reference = diffrax.diffeqsolve(
        term, diffrax.Dopri8(), 0.0, 1.0, 0.001, (jnp.array([1.0]), jnp.array([0.0])),
        args=110.0, stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=10_000, saveat=diffrax.SaveAt(t1=True)).ys[0]
    retried_error = float(jnp.max(jnp.abs(retried.ys[0] - reference)))
    assert retried_error <= float(jnp.max(jnp.abs(chord.ys[0] - reference)))


def test_picard_fallback_needs_picard():
    with pytest.raises(ValueError, match="picard_fallback"):
        ChordIteration(picard_fallback=True)
    with pytest.raises(TypeError, match="picard_fallback"):
        dvi.RoundoffNewton(picard=True, picard_fallback=1)


@pytest.mark.parametrize("degree", [6, 9])
def test_a_solve_on_the_engine_compiles_without_library_calls(degree):
    """A whole solve on the engine, its Newton fallback included, holds no LAPACK call and no
    product for the dot library (Kepler, whose Lagrangian has none of its own): XLA's CPU
    backend can then compile the solve's loop whole, without a runtime dispatch per
    operation, where `xla_cpu_small_while_loop_byte_threshold` lets it (the benchmarks
    page). One such call anywhere in the step would keep the whole loop out of that. (At
    degree 9 the fallback's Jacobian, formed as one batch of derivatives, had two.)"""
    problem = problems.kepler(eccentricity=0.5)

    def run(y0):
        return diffrax.diffeqsolve(problem.term, dvi.CGVI(degree, root_finder=FALLBACK), 0.0, 1.0,
                                   0.1, y0, max_steps=16, saveat=diffrax.SaveAt(t1=True),
                                   throw=False).ys  # (`throw` adds a callback after the loop)

    text = jax.jit(run).lower(problem.y0).compile().as_text()
    assert "custom-call" not in text and "kind=kCustom" not in text


@pytest.mark.parametrize("dtype, bound", [(jnp.float32, 1e-5), (jnp.float16, 2e-2)])
def test_lower_precisions(dtype, bound):
    problem = problems.harmonic_oscillator(dtype=dtype)
    solver = dvi.CGVI(4, root_finder=ENGINE)
    ctx = solver.step_context(problem.term, dtype(0), dtype(0.1), problem.y0, problem.args)
    assert solver.seeder.engine(ctx) is not None
    sol = diffrax.diffeqsolve(
        problem.term, solver, dtype(0), dtype(1), dtype(0.1), problem.y0, args=problem.args,
        saveat=diffrax.SaveAt(ts=jnp.asarray(problem.ts, dtype)),
    )
    assert sol.ys[0].dtype == dtype
    q_ref, _ = problem.reference(np.asarray(sol.ts, np.float64))
    assert np.max(np.abs(np.asarray(sol.ys[0], np.float64) - q_ref)) <= bound


def _oscillator_energy_errors(steps):
    problem = problems.harmonic_oscillator()
    h = 0.5
    sol = diffrax.diffeqsolve(problem.term, dvi.CGVI(7, root_finder=ENGINE), 0.0, steps * h, h,
                              problem.y0, args=problem.args, max_steps=steps,
                              saveat=diffrax.SaveAt(steps=True))
    e0 = float(problem.energy(0.0, *problem.y0))
    energy = jax.vmap(lambda q, p: problem.energy(0.0, q, p))(sol.ys[0], sol.ys[1])
    return np.asarray(sol.ts), np.abs(np.asarray(energy) - e0) / abs(e0)


@pytest.mark.slow
def test_energy_error_stays_at_round_off():
    # CGVI(7), oscillator, h = 0.5: the bound of the chord iteration's long-run test
    # (tests/test_methods.py) holds over ten times the steps. An iteration whose result
    # carries an error of the same sign on every step (constants rounded once, or a stop one
    # update early) grows linearly instead and exceeds it.
    _, errors = _oscillator_energy_errors(200_000)
    assert errors.max() <= 1e-13


@pytest.mark.long
def test_energy_error_follows_brouwers_law():
    # 10^6 steps from 24 initial states (benchmarks/engine_energy_growth.py, one vmapped
    # solve): the running maximum grows as a random walk's (exponent 1/2), not linearly. One
    # run's exponent scatters by about 0.13 even for a true random walk, so the claim is the
    # mean over the runs, at most 0.6, beside the same fit on 200 random walks sampled at the
    # same points. The calibration must put 0.6 at least three standard errors (of a mean of
    # as many walks) above the walks' mean: a true random walk then passes with probability
    # above 99.8 %, and a failure says the growth is not a random walk's.
    from benchmarks import engine_energy_growth as study

    ts, errors, _ = study.energy_error_runs(1_000_000)
    assert errors.shape[0] >= 8
    assert errors[:, :study.EARLY_STEPS].max() <= study.EARLY_BOUND  # 5e-14 over 2·10^4 steps
    found = study.calibration(study.run_exponents(ts, errors),
                              study.random_walk_exponents(ts, 200))
    assert found["bound_z"] >= 3, found
    assert found["mean"] <= study.BOUND, found  # 0.6


def test_picard_must_be_a_bool():
    with pytest.raises(TypeError, match="picard"):
        ChordIteration(picard="yes")
    with pytest.raises(TypeError, match="restart must be True or False"):
        dvi.RoundoffNewton(restart=1)


def test_the_iteration_refuses_a_step_without_its_update():
    # Given alone to a step that offers no constant-matrix update, it says what is missing.
    def residual(z, args):
        return z, None

    with pytest.raises(ValueError, match="needs the hint `update`"):
        one_step_solve(JacobianFreeIteration(), residual, (jnp.ones((2, 1)), jnp.ones(1)), None,
                       step_options(StepHints(max_iterations=10)))


def test_the_end_increment_is_summed_without_rounding():
    """`end_increments` sums `Σ_k gd_k δc_k` to within a rounding unit of the exact sum even
    where the terms cancel (where the plain sum is off by many), and differentiates as the
    plain sum."""
    import types
    from fractions import Fraction

    from diffrax_vi._step.jacobian_free import end_increments

    rng = np.random.default_rng(3)
    gd = rng.normal(size=(2, 7))  # (D, k)
    dc = rng.normal(size=(7, 2))
    # make the sums cancel: the last direction nearly undoes the others
    dc[6] = -(np.einsum("dk,kd->d", gd[:, :6], dc[:6]) / gd[:, 6]) * (1 + 1e-9)
    engine = types.SimpleNamespace(span=types.SimpleNamespace(gd=gd))
    ctx = types.SimpleNamespace(q0=jnp.zeros(2), p0=jnp.zeros(2))
    z = (jnp.asarray(dc), jnp.zeros(2))
    dq, _ = end_increments(engine, ctx, z)
    eps = float(np.finfo(np.float64).eps)
    plain = np.einsum("dk,kd->d", gd, dc)
    for d in range(2):
        exact = sum(Fraction(float(gd[d, k])) * Fraction(float(dc[k, d])) for k in range(7))
        size = sum(abs(gd[d, k] * dc[k, d]) for k in range(7))
        assert abs(Fraction(float(dq[d])) - exact) <= abs(exact) * eps + 16 * eps**2 * size
        assert abs(Fraction(float(plain[d])) - exact) > 100 * abs(exact) * eps  # not trivial
    grad = jax.jacfwd(lambda c: end_increments(engine, ctx, (c, z[1]))[0])(z[0])
    np.testing.assert_array_equal(grad, jax.jacfwd(lambda c: jnp.einsum("dk,kd->d", gd, c))(z[0]))
