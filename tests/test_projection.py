"""VariableProjection and RoundoffNewton: the well-posed network step."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._step.formulation import StepContext
from tests.helpers import max_relative_error, solve_problem


def projected(activation, width, nodes, **kwargs):
    return dvi.NetworkVI(
        dvi.ShallowNetBasis(activation, width),
        dvi.GaussLegendre(nodes),
        formulation=dvi.VariableProjection(**kwargs),
    )


solve = solve_problem


def residual_scale(y0):
    q, p = y0
    return 1 + max(float(jnp.max(jnp.abs(q))), float(jnp.max(jnp.abs(p))))


@pytest.mark.parametrize("activation", [
    dvi.tanh,
    # (the other activations' projected step: test_activation_recognition.py's energy test)
    *(pytest.param(a, marks=pytest.mark.slow) for a in (dvi.gelu, dvi.sigmoid)),
])
def test_oscillator_to_round_off_in_one_iteration(activation):
    # A quadratic Lagrangian makes the projected equations linear: one Newton update solves
    # them, and the residual left is rounding (issue 27: max error <= 2e-14, final <= 1e-14);
    # the network's Newton iteration does not confirm it (`confirm=False`, as the default
    # root finder has it where the kinetic matrix is not constant).
    problem = problems.harmonic_oscillator()
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(activation, 10), dvi.GaussLegendre(8),
        formulation=dvi.VariableProjection(), iteration_log=10,
        root_finder=dvi.RoundoffNewton(confirm=False),
    )
    sol = solve(problem, solver)
    assert sol.result == diffrax.RESULTS.successful
    assert max_relative_error(problem, sol) <= 2e-14
    q_ref, _ = problem.reference(np.asarray(sol.ts[-1:]))
    assert abs(float(sol.ys[0][-1, 0]) - q_ref[0, 0]) / abs(q_ref[0, 0]) <= 1e-14
    state = sol.solver_state
    assert np.all(np.asarray(state.iteration_log) == 1)
    assert not solver.root_finder.confirm
    eps = float(jnp.finfo(jnp.float64).eps)
    assert float(state.report.residual) <= 64 * eps * residual_scale(problem.y0)


def test_oscillator_long_steps_and_energy():
    # h = 0.5 over 200 steps: error <= 1e-12; the energy error stays bounded (no drift).
    problem = problems.harmonic_oscillator().with_span(n_steps=2000, dt=0.5)
    solver = projected(dvi.tanh, 10, 8)
    ts = jnp.asarray(problem.t0 + 0.5 * np.arange(0, 2001, 10))
    sol = diffrax.diffeqsolve(
        problem.term, solver, problem.t0, problem.t1, problem.dt, problem.y0,
        args=problem.args, saveat=diffrax.SaveAt(ts=ts), max_steps=2100,
    )
    assert sol.result == diffrax.RESULTS.successful
    q_ref, _ = problem.reference(np.asarray(ts))
    q = np.asarray(sol.ys[0])
    assert np.max(np.abs(q[:21] - q_ref[:21])) / np.max(np.abs(q_ref)) <= 1e-12  # T = 100
    energy = np.asarray(jax.vmap(lambda q, p: problem.energy(0.0, q, p))(*sol.ys))
    relative = np.abs(energy - energy[0]) / abs(energy[0])
    assert relative.max() <= 1e-12


def test_double_pendulum_in_few_iterations():
    problem = problems.double_pendulum(t1=1.0, dt=0.1)
    sol = solve(problem, projected(dvi.tanh, 10, 16))
    eps = float(jnp.finfo(jnp.float64).eps)
    assert float(sol.solver_state.report.residual) <= 64 * eps * 10
    assert sol.result == diffrax.RESULTS.successful
    assert max_relative_error(problem, sol) <= 1e-11
    hist = np.asarray(sol.solver_state.histogram)
    median = int(np.searchsorted(np.cumsum(hist), hist.sum() / 2))
    assert median <= 3
    assert int(sol.solver_state.max_iterations) <= 4


def test_converged_parameters_are_the_curve():
    # The output weights expanded from the span coordinates give a network whose end value is
    # the step's q_{n+1}: dense output and the next step's seed read a network again.
    problem = problems.double_pendulum(t1=0.2, dt=0.1)
    solver = projected(dvi.tanh, 10, 16)
    sol = solve(problem, solver)
    theta = sol.solver_state.theta
    q_end = solver.basis.evaluate(theta, jnp.ones(()))
    np.testing.assert_allclose(q_end, sol.ys[0][-1], rtol=0, atol=1e-12)


@pytest.mark.slow  # dense output of the default (projected) step: test_solver.py
def test_dense_output_inside_a_step():
    problem = problems.harmonic_oscillator()
    solver = projected(dvi.tanh, 12, 10)
    sol = diffrax.diffeqsolve(
        problem.term, solver, problem.t0, problem.t1, problem.dt, problem.y0,
        saveat=diffrax.SaveAt(dense=True),
    )
    q_ref, _ = problem.reference(np.array([0.35]))
    q, _ = sol.evaluate(0.35)
    assert abs(float(q[0]) - q_ref[0, 0]) <= 1e-9


def _context(problem, solver, theta_like_width=10):
    q0, p0 = problem.y0
    ctx = solver.step_context(problem.term, 0.0, 0.1, problem.y0, problem.args)
    key = jax.random.PRNGKey(0)
    theta = jax.random.normal(key, (3 * theta_like_width, q0.shape[0]), dtype=q0.dtype)
    return ctx, theta


def test_closed_form_jacobian_matches_autodiff():
    problem = problems.double_pendulum()
    solver = projected(dvi.tanh, 10, 16)
    ctx, theta = _context(problem, solver)
    assert isinstance(ctx, StepContext)
    form = solver.formulation

    @jax.jit  # one program, not one per JAX operation
    def both(theta):
        span = form.span(theta, ctx)
        start = form.reduce(lambda tau: solver.basis.evaluate(theta, tau), span, ctx)
        z = (start, problem.y0[1] + 0.1)
        flat, unravel = jax.flatten_util.ravel_pytree(z)

        def residual(v):
            return jax.flatten_util.ravel_pytree(
                form.reduced_residual(unravel(v), (ctx, span)))[0]

        return form.reduced_jacobian(z, (ctx, span)), jax.jacfwd(residual)(flat)

    closed_form, expected = both(theta)
    np.testing.assert_allclose(closed_form, expected, atol=1e-12)


def test_span_is_orthonormal_in_the_quadrature_norm():
    problem = problems.double_pendulum()
    solver = projected(dvi.tanh, 10, 16)
    ctx, theta = _context(problem, solver)
    span = solver.formulation.span(theta, ctx)
    # Direction 0 is the constant function, exactly: value 1, slope 0, no change over the step.
    assert bool(jnp.all(span.gq[:, :, 0] == 1)) and bool(jnp.all(span.gv[:, :, 0] == 0))
    assert bool(jnp.all(span.g0[:, 0] == 1)) and bool(jnp.all(span.gd[:, 0] == 0))
    root_b = jnp.sqrt(ctx.weights)[None, :, None]
    data = jnp.concatenate(
        [root_b * span.gq, root_b * span.gv, span.g0[:, None], span.g1[:, None]], axis=1
    )
    gram = jnp.einsum("dik,dil->dkl", data, data)
    live = span.live.T  # (D, k)
    # orthogonal; the others orthonormal, the constant of norm² Σ b + 2 = 3
    norms = jnp.ones(gram.shape[-1]).at[0].set(3.0)
    expected = jnp.where(live[:, :, None] & live[:, None, :], jnp.diag(norms), 0)
    mask = live[:, :, None] & live[:, None, :]
    np.testing.assert_allclose(jnp.where(mask, gram, 0), expected, atol=1e-12)
    # The expansion reproduces the span directions through the network's own features, up
    # to the rounding of a direction's output weights (eps / s_k of it, with s_k / s_1 down
    # to the rank threshold eps^(5/8)) and to how well the features fit the constant
    # (direction 0, exact in the span; each direction is made orthogonal to it).
    taus = jnp.concatenate([ctx.nodes, jnp.array([0.0, 1.0])])
    def curve_of(c):
        theta_c = solver.formulation.expand(c, span)
        return jax.vmap(solver.basis.evaluate, in_axes=(None, 0))(theta_c, taus)

    one = jnp.zeros_like(span.g0.T).at[0].set(1.0)
    misfit = jnp.max(jnp.abs(curve_of(one) - 1), axis=0)  # (D,)
    c = jnp.where(span.live, 1.0, 0.0)
    expected = jnp.concatenate([jnp.einsum("djk,kd->jd", span.gq, c), (span.g0.T * c).sum(0)[None],
                                (span.g1.T * c).sum(0)[None]])
    shift = jnp.abs(span.to_alpha[:, :, 1:]).sum(1).max(1) / jnp.abs(span.to_alpha[:, :, 0]).max(1)
    eps = float(jnp.finfo(jnp.float64).eps)
    bound = 10 * eps / eps**0.625 + misfit * (1 + shift)
    assert bool(jnp.all(jnp.abs(curve_of(c) - expected) <= bound))


def test_a_polynomial_curve_is_sampled_by_constant_matrices():
    """A polynomial's curve at the nodes and ends, by `sample_matrices` (NumPy, constants of
    the program), equals the curve evaluated, and the projected start it gives equals the
    start of the curve itself to rounding."""
    from diffrax_vi._step.formulation import CurveSamples

    problem = problems.double_pendulum()
    solver = dvi.CGVI(6)
    ctx, theta = _context(problem, solver)
    theta = jnp.asarray(np.random.default_rng(0).normal(size=(7, 2)))
    taus = np.concatenate([np.asarray(ctx.nodes), [0.0, 1.0]])
    values, slopes = solver.basis.sample_matrices(taus)
    assert isinstance(values, np.ndarray) and values.shape == slopes.shape == (len(taus), 7)

    def curve(tau):
        return solver.basis.evaluate(theta, tau)

    evaluated = CurveSamples.of(curve, ctx.nodes)
    r = len(ctx.nodes)
    sampled = CurveSamples((values @ theta)[:r], (slopes @ theta)[:r], (values @ theta)[r:])
    for a, b in zip(sampled, evaluated, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)
    span = solver.formulation.span(ctx.basis.zeros(2, jnp.float64), ctx)
    p1 = ctx.p0 + 0.1
    by_samples = solver.formulation.start(sampled, p1, span, ctx)
    by_curve = solver.formulation.start(curve, p1, span, ctx)
    for a, b in zip(by_samples, by_curve, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)
    assert dvi.ShallowNetBasis(dvi.tanh, 4).sample_matrices(taus) is None


def test_uniform_layer_features_hold_the_constant():
    # The default hidden layers fit the constant direction to 1e-10: the network that
    # the step hands to dense output is the solved curve to that, relative to |q|.
    problem = problems.double_pendulum()
    for activation, width in ((dvi.tanh, 10), (dvi.sigmoid, 10), (dvi.gelu, 8)):
        solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, width), dvi.GaussLegendre(8))
        ctx = solver.step_context(problem.term, 0.0, 0.1, problem.y0, problem.args)
        theta = dvi.UniformLayer().parameters(solver.basis, 2, jnp.float64)
        span = solver.formulation.span(theta, ctx)
        one = jnp.zeros_like(span.g0.T).at[0].set(1.0)
        values = jax.vmap(solver.basis.evaluate, in_axes=(None, 0))(
            solver.formulation.expand(one, span), jnp.linspace(0.0, 1.0, 51)
        )
        assert float(jnp.max(jnp.abs(values - 1))) <= 1e-10, activation


def test_vmap_matches_loop_on_the_oscillator():
    # issue 27: four amplitudes under vmap equal the loop of single solves to 1e-14
    problem = problems.harmonic_oscillator()
    solver = projected(dvi.tanh, 10, 8)
    run = eqx.filter_jit(
        lambda y: diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, problem.dt, y, args=problem.args,
            saveat=diffrax.SaveAt(ts=jnp.asarray(problem.ts)),
        ).ys
    )
    amplitudes = jnp.array([0.3, 0.5, 0.7, 0.9])
    loop = [run((a[None], jnp.zeros(1))) for a in amplitudes]
    batched = jax.vmap(lambda a: run((a[None], jnp.zeros(1))))(amplitudes)
    for i in range(2):
        np.testing.assert_allclose(
            np.asarray(batched[i]), np.stack([np.asarray(y[i]) for y in loop]), rtol=0,
            atol=1e-14,
        )


def test_degenerate_pendulum():
    # The IODE pendulum (gelu 8, GL8): issue 27's bound. The end correction of a first-order
    # Lagrangian carries it (3.0e-8 without: the span's derivative defect enters q2 linearly).
    problem = problems.pendulum()
    sol = solve(problem, projected(dvi.gelu, 8, 8))
    assert sol.result == diffrax.RESULTS.successful
    assert max_relative_error(problem, sol) <= 1e-9


@pytest.mark.slow  # vmap against the loop: the oscillator above
def test_vmap_matches_loop_on_the_double_pendulum():
    problem = problems.double_pendulum(t1=0.5, dt=0.1)
    solver = projected(dvi.tanh, 10, 16)
    run = eqx.filter_jit(
        lambda y: diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, problem.dt, y, args=problem.args,
        ).ys[0][-1]
    )
    q0, p0 = problem.y0
    starts = jnp.stack([q0 * s for s in (0.9, 1.0, 1.1)])
    loop = np.stack([np.asarray(run((q, p0))) for q in starts])
    batched = np.asarray(jax.vmap(lambda q: run((q, p0)))(starts))
    assert np.all(np.isfinite(batched))
    np.testing.assert_allclose(batched, loop, rtol=0, atol=1e-14)


def _restart_run(problem, restart=True, controller=None):
    def run(y, max_steps=256):
        solver = dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(16),
            root_finder=dvi.RoundoffNewton(confirm=False, picard=True, restart=restart),
            root_find_max_steps=max_steps,
        )
        sol = diffrax.diffeqsolve(
            problem.term, solver, 0.0, 5.0, 1.0, y, args=problem.args, throw=False,
            saveat=diffrax.SaveAt(t1=True, solver_state=True), max_steps=64,
            stepsize_controller=controller or diffrax.ConstantStepSize(),
        )
        return sol.ys[0][-1], sol.result, sol.solver_state.restarts

    return run


def test_restart_from_the_trajectory_seed():
    # The double pendulum at h = 1: on some steps the start from the previous curve does not
    # converge within the first try, and the restart from the trajectory seed does.
    problem = problems.double_pendulum()
    q, result, restarts = eqx.filter_jit(_restart_run(problem))(problem.y0)
    assert result == diffrax.RESULTS.successful
    assert int(restarts) >= 1 and np.all(np.isfinite(np.asarray(q)))


def test_without_the_restart_such_a_step_fails_and_is_retried():
    # The default (`restart=False`): the same run fails loudly at a constant step, and
    # `RetryFailedSteps` takes the steps that failed in pieces and reaches t1 at least as
    # close to the motion as the run with the restart (its pieces are shorter steps).
    problem = problems.double_pendulum()
    reference = diffrax.diffeqsolve(
        problem.term, diffrax.Dopri8(), 0.0, 5.0, 1e-3, problem.y0, args=problem.args,
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12), max_steps=100_000,
    ).ys[0][-1]
    with_restart, _, _ = eqx.filter_jit(_restart_run(problem))(problem.y0)
    _, result, restarts = eqx.filter_jit(_restart_run(problem, restart=False))(problem.y0)
    assert result != diffrax.RESULTS.successful and int(restarts) == 0
    retried = _restart_run(problem, restart=False, controller=dvi.RetryFailedSteps())
    q, result, restarts = eqx.filter_jit(retried)(problem.y0)
    assert result == diffrax.RESULTS.successful and int(restarts) == 0
    error = float(jnp.max(jnp.abs(q - reference)))
    assert error <= float(jnp.max(jnp.abs(with_restart - reference)))


@pytest.mark.slow  # the restart itself: the test above; here under vmap and without a second try
def test_restart_under_vmap_and_without_a_second_try():
    problem = problems.double_pendulum()
    run = _restart_run(problem)
    # a member that restarts and one that does not, in one batch, as in a loop
    q0, p0 = problem.y0
    scales = jnp.array([0.1, 1.0])
    loop = [eqx.filter_jit(run)((q0 * s, p0 * s)) for s in scales]
    batched = eqx.filter_jit(jax.vmap(lambda s: run((q0 * s, p0 * s))))(scales)
    assert [int(r) for _, _, r in loop] == [int(r) for r in batched[2]]
    assert int(loop[0][2]) == 0 < int(loop[1][2])
    np.testing.assert_allclose(
        np.asarray(batched[0]), np.stack([np.asarray(q) for q, _, _ in loop]), rtol=0, atol=1e-14
    )
    # with no iterations left for a second try (cap <= first try) the same solve fails
    _, result, restarts = eqx.filter_jit(run)(problem.y0, max_steps=16)
    assert result != diffrax.RESULTS.successful and int(restarts) == 0


@pytest.mark.slow  # the projected step's gradient: test_solver_interop.py's finite-difference test
def test_gradient_through_projected_steps():
    # d q(T) / d q0 of the oscillator is cos(T); implicit differentiation of each projected
    # step's square system gives it.
    term = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 0.5 * q @ q)
    solver = projected(dvi.tanh, 12, 10)

    def end(q0):
        sol = diffrax.diffeqsolve(term, solver, 0.0, 0.5, 0.1, (q0, jnp.zeros(1)))
        return sol.ys[0][-1, 0]

    grad = jax.grad(end)(jnp.array([0.5]))
    assert abs(float(grad[0]) - np.cos(0.5)) <= 1e-10


def test_float32_stays_float32():
    problem = problems.harmonic_oscillator(dtype=jnp.float32)
    solver = projected(dvi.tanh, 10, 8)
    sol = diffrax.diffeqsolve(
        problem.term, solver, jnp.float32(0), jnp.float32(1), jnp.float32(0.1),
        problem.y0, args=problem.args,
    )
    assert sol.ys[0].dtype == jnp.float32
    assert sol.result == diffrax.RESULTS.successful
    q_ref, _ = problem.reference(np.array([1.0]))
    assert abs(float(sol.ys[0][-1, 0]) - q_ref[0, 0]) <= 1e-5


def test_non_finite_step_fails():
    # The force blows up at q = 0, which the motion crosses: the step must fail, never return
    # NaN as a success.
    term = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - jnp.sum(jnp.log(q)))
    solver = projected(dvi.tanh, 10, 8)
    sol = diffrax.diffeqsolve(
        term, solver, 0.0, 1.0, 0.5, (jnp.array([0.05]), jnp.array([-3.0])), throw=False
    )
    finite = bool(np.all(np.isfinite(np.asarray(sol.ys[0]))))
    assert sol.result != diffrax.RESULTS.successful or finite


def test_refusals():
    with pytest.raises(ValueError, match="ShallowNetBasis without mirrored pairs"):
        dvi.NetworkVI(
            dvi.DenseNetBasis(dvi.tanh, 4, 4), formulation=dvi.VariableProjection(),
            seed=dvi.SeedPolicy(initial_guess=dvi.LSGD()),
        )
    with pytest.raises(ValueError, match="ShallowNetBasis without mirrored pairs"):
        dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, 10, symmetry=dvi.MirrorPairs()),
            formulation=dvi.VariableProjection(),
        )
    with pytest.raises(ValueError, match="exceeds the 6 features"):
        projected(dvi.tanh, 6, 8, rank=7)
    with pytest.raises(ValueError, match="exceeds the 4 features"):
        dvi.NetworkVI(dvi.LagrangeBasis(3), formulation=dvi.VariableProjection(rank=5))
    with pytest.raises(ValueError, match="no hidden layer"):
        dvi.NetworkVI(
            dvi.LagrangeBasis(3), formulation=dvi.VariableProjection(hidden=dvi.SeedLayer()),
            seed=dvi.SeedPolicy(initial_guess=dvi.LeastSquaresFit()),
        )
    with pytest.raises(ValueError, match="RoundoffNewton"):
        dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, 10), formulation=dvi.VariableProjection(),
            root_finder=dvi.LevenbergMarquardt(),
        )
    with pytest.raises(ValueError, match="rank"):
        dvi.VariableProjection(rank=0)
    with pytest.raises(ValueError, match="rtol"):
        dvi.VariableProjection(rtol=2.0)


def test_default_root_finder_follows_the_formulation():
    basis = dvi.ShallowNetBasis(dvi.tanh, 10)
    default = dvi.NetworkVI(basis)
    assert default.formulation == dvi.VariableProjection()
    assert isinstance(default.root_finder, dvi.RoundoffNewton)
    solver = dvi.NetworkVI(basis, formulation=dvi.FreeEndpoints())
    assert isinstance(solver.root_finder, dvi.LevenbergMarquardt)


@pytest.mark.parametrize(
    "basis, options",
    [
        (dvi.ShallowNetBasis(dvi.tanh, 10), dict(root_finder=dvi.LevenbergMarquardt())),
        (dvi.ShallowNetBasis(dvi.tanh, 10), dict(seed=dvi.SeedPolicy(reuse_neurons=True))),
        (dvi.ShallowNetBasis(dvi.tanh, 10), dict(seed=dvi.SeedPolicy(dvi.PreviousStep()))),
        (dvi.ShallowNetBasis(dvi.tanh, 10),
         dict(seed=dvi.SeedPolicy(initial_guess=dvi.oga.OGA2d()))),
        (dvi.ShallowNetBasis(dvi.tanh, 10),
         dict(seed=dvi.SeedPolicy(initial_guess=dvi.oga.OGA1d(dict_amount=400)))),
        (dvi.ShallowNetBasis(dvi.tanh, 10),
         dict(seed=dvi.SeedPolicy(initial_guess=dvi.oga.OGA1d(bias_interval=(-2, 2))))),
        (dvi.ShallowNetBasis(dvi.sin, 10), {}),  # equal |w|: two features span everything
        (dvi.ShallowNetBasis(dvi.relu_k(1), 10), {}),
        (dvi.ShallowNetBasis(dvi.tanh, 4, symmetry=dvi.MirrorPairs()), {}),
        (dvi.DenseNetBasis(dvi.tanh, 4, 4), dict(seed=dvi.SeedPolicy(initial_guess=dvi.LSGD()))),
    ],
)
def test_default_formulation_is_all_parameter_where_the_projection_does_not_apply(
    basis, options
):
    solver = dvi.NetworkVI(basis, **options)
    assert solver.formulation == dvi.FreeEndpoints()


@pytest.mark.parametrize("activation", [dvi.tanh, dvi.sigmoid, dvi.gelu, dvi.relu_k(3)])
def test_default_formulation_is_the_projection_for_the_activations_it_suits(activation):
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, 8))
    assert solver.formulation == dvi.VariableProjection()
    # the projected step restarts from the initial trajectory: choosing one keeps it
    trajectory = dvi.IntegratorExtrapolation(substeps=20)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, 8),
                           seed=dvi.SeedPolicy(initial_trajectory=trajectory))
    assert solver.formulation == dvi.VariableProjection()


def test_the_fixed_layer_refuses_seed_options_it_would_ignore():
    basis = dvi.ShallowNetBasis(dvi.tanh, 10)
    with pytest.raises(ValueError, match="initial_guess would have no effect"):
        dvi.NetworkVI(basis, formulation=dvi.VariableProjection(),
                      seed=dvi.SeedPolicy(initial_guess=dvi.oga.OGA2d()))
    seeded = dvi.VariableProjection(hidden=dvi.SeedLayer())
    solver = dvi.NetworkVI(basis, formulation=seeded,
                           seed=dvi.SeedPolicy(initial_guess=dvi.oga.OGA1d(dict_amount=400)))
    assert solver.seed.initial_guess.dict_amount == 400


@pytest.mark.long
def test_first_seed_layer_is_one_compiled_path_for_vmap_and_loop():
    # With the first step's hidden layer kept, every later step starts from the previous
    # curve continued and solves on the same span: no per-step seed fit whose greedy choices
    # can differ between a lane of a vmap and a single solve.
    problem = problems.harmonic_oscillator()
    solver = projected(dvi.tanh, 10, 8, hidden=dvi.FirstSeedLayer())
    run = eqx.filter_jit(
        lambda y: diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, problem.dt, y, args=problem.args,
            saveat=diffrax.SaveAt(ts=jnp.asarray(problem.ts), solver_state=True),
        )
    )
    amplitudes = jnp.array([0.3, 0.5, 0.7, 0.9])
    loop = np.stack([np.asarray(run((a[None], jnp.zeros(1))).ys[0]) for a in amplitudes])
    batched = jax.vmap(lambda a: run((a[None], jnp.zeros(1))))(amplitudes)
    np.testing.assert_allclose(np.asarray(batched.ys[0]), loop, rtol=0, atol=1e-14)
    steps = len(problem.ts) - 1
    assert np.all(np.asarray(batched.solver_state.warm_starts) == steps - 1)
    assert np.all(np.asarray(batched.solver_state.max_iterations) == 1)
    sol = run(problem.y0)
    assert max_relative_error(problem, sol) <= 1e-11


def test_hidden_layer_rules_are_checked():
    with pytest.raises(TypeError, match="hidden must be"):
        dvi.VariableProjection(hidden="uniform")
    with pytest.raises(ValueError, match="scale"):
        dvi.UniformLayer(scale=0.0)
    with pytest.raises(ValueError, match="centres"):
        dvi.UniformLayer(centres=(1.0, -1.0))
    with pytest.raises(ValueError, match="centres"):
        dvi.UniformLayer(centres=(0.0, 1.0, 2.0))


def test_roundoff_newton_settings_are_checked():
    with pytest.raises(ValueError, match="ftol"):
        dvi.RoundoffNewton(ftol=-1)
    dvi.RoundoffNewton(ftol=0)  # allowed: run every solve to round-off
    with pytest.raises(ValueError, match="floor"):
        dvi.RoundoffNewton(ftol=64, floor=8)
    with pytest.raises(ValueError, match="max_stalls"):
        dvi.RoundoffNewton(max_stalls=0)


def test_roundoff_newton_without_tolerance_runs_to_the_floor():
    # ftol=0: a solve ends only once its updates stop shrinking, so even the oscillator's
    # linear step (one update reaches the root) takes more than one iteration.
    problem = problems.harmonic_oscillator()
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8),
        root_finder=dvi.RoundoffNewton(ftol=0.0), iteration_log=10,
    )
    sol = solve(problem, solver)
    assert sol.result == diffrax.RESULTS.successful
    assert np.all(np.asarray(sol.solver_state.iteration_log) >= 2)
    assert max_relative_error(problem, sol) <= 2e-14


def test_projection_refuses_the_all_parameter_seed_options():
    basis = dvi.ShallowNetBasis(dvi.tanh, 10)
    with pytest.raises(ValueError, match="all-parameter"):
        dvi.NetworkVI(basis, formulation=dvi.VariableProjection(),
                      seed=dvi.SeedPolicy(reuse_neurons=True))
    with pytest.raises(ValueError, match="all-parameter"):
        dvi.NetworkVI(
            basis, formulation=dvi.VariableProjection(),
            seed=dvi.SeedPolicy(initial_trajectory=dvi.PreviousStep()),
        )


def test_uniform_layer_is_centred_where_asked():
    basis = dvi.ShallowNetBasis(dvi.tanh, 4)
    theta = dvi.UniformLayer(scale=0.5, centres=(-1.0, 2.0)).parameters(basis, 2, jnp.float64)
    alpha, w, beta = basis.split(theta)
    np.testing.assert_array_equal(alpha, 0)
    np.testing.assert_allclose(w[:, 0], [0.5, -0.5, 0.5, -0.5])
    np.testing.assert_allclose(-beta[:, 1] / w[:, 1], [-1.0, 0.0, 1.0, 2.0])


def test_seed_layer_refits_every_step():
    problem = problems.double_pendulum(t1=0.3, dt=0.1)
    sol = solve(problem, projected(dvi.tanh, 10, 16, hidden=dvi.SeedLayer()))
    assert sol.result == diffrax.RESULTS.successful
    assert int(sol.solver_state.warm_starts) == 0
    assert max_relative_error(problem, sol) <= 1e-11


def test_float16_makes_a_newton_update_on_every_step():
    # In float16 the tolerance (64 eps, about 0.06 of the residual scale) can be as large as
    # the start's residual: the step must still solve, not accept its start.
    problem = problems.harmonic_oscillator(dtype=jnp.float16)
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8),
        formulation=dvi.VariableProjection(), iteration_log=10,
    )
    f16 = jnp.float16
    sol = diffrax.diffeqsolve(
        problem.term, solver, f16(0), f16(1), f16(0.1), problem.y0, args=problem.args,
        saveat=diffrax.SaveAt(ts=jnp.asarray(problem.ts, f16), solver_state=True),
    )
    assert sol.ys[0].dtype == jnp.float16
    assert np.all(np.asarray(sol.solver_state.iteration_log) >= 1)
    assert max_relative_error(problem, sol) <= 1e-2


@pytest.mark.parametrize("activation, width, bound", [(dvi.tanh, 10, 1e-13), (dvi.gelu, 8, 4e-9)])
def test_first_order_lagrangian_keeps_its_primary_constraint(activation, width, bound):
    # issue 29's degenerate example: L = q0 v1 - |q|²/2 (a rotation; p = (0, q0) along it).
    # The all-parameter step let p - ϑ(q) grow to 1e-6 here at small residuals; the end
    # correction takes q_{n+1}[0] from p_{n+1}[1].
    term = dvi.LagrangianTerm(lambda t, q, v, args: q[0] * v[1] - 0.5 * q @ q)
    y0 = (jnp.array([0.5, 0.2]), jnp.array([0.0, 0.5]))
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, width))
    sol = diffrax.diffeqsolve(term, solver, 0.0, 2.0, 0.1, y0, saveat=diffrax.SaveAt(steps=True))
    assert sol.result == diffrax.RESULTS.successful
    steps = int(sol.stats["num_accepted_steps"])
    t = np.asarray(sol.ts)[:steps]
    exact = np.stack([0.5 * np.cos(t) - 0.2 * np.sin(t), 0.2 * np.cos(t) + 0.5 * np.sin(t)], 1)
    q, p = np.asarray(sol.ys[0])[:steps], np.asarray(sol.ys[1])[:steps]
    assert np.max(np.abs(q - exact)) <= bound
    # the constraint's read part holds exactly; p0 (= 0 along the flow) is the step's natural
    # boundary value, as accurate as the step
    np.testing.assert_array_equal(p[:, 1], q[:, 0])
    assert np.max(np.abs(p[:, 0])) <= bound


FREE_PARTICLE = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v)


@pytest.mark.parametrize("case", ["cgvi double pendulum", "cgvi free particle", "network"])
def test_reduced_jacobian_and_its_unpivoted_inverse(case):
    """The Jacobian matches autodiff, also on a span that is the same in every coordinate
    (`CGVI`: one product of constants with the Hessians), and `reduced_inverse` inverts it,
    also for a free particle, whose constant direction has a zero diagonal entry."""
    if case == "network":
        problem, solver = problems.double_pendulum(), projected(dvi.tanh, 10, 16)
        term, y0, args = problem.term, problem.y0, problem.args
    else:
        solver = dvi.CGVI(6)
        if case == "cgvi free particle":
            term, y0, args = FREE_PARTICLE, (jnp.array([0.3, -0.2]), jnp.array([1.0, 0.5])), None
        else:
            problem = problems.double_pendulum()
            term, y0, args = problem.term, problem.y0, problem.args
    ctx = solver.step_context(term, 0.0, 0.1, y0, args)
    theta = jax.random.normal(jax.random.PRNGKey(0), (30, 2), dtype=y0[0].dtype)
    form = solver.formulation
    span = form.span(theta, ctx)
    assert form.uniform_span(span) == (case != "network")
    start = form.reduce(lambda tau: y0[0] + 0.3 * tau + 0.1 * tau**3, span, ctx)
    z = (start, y0[1] + 0.1)
    flat, unravel = jax.flatten_util.ravel_pytree(z)

    def residual(v):
        return jax.flatten_util.ravel_pytree(form.reduced_residual(unravel(v), (ctx, span)))[0]

    jacobian = jax.jit(lambda z: form.reduced_jacobian(z, (ctx, span)))(z)
    expected = jax.jit(jax.jacfwd(residual))(flat)
    np.testing.assert_allclose(jacobian, expected, rtol=0,
                               atol=1e-12 * float(jnp.max(jnp.abs(expected))))
    inverse = jax.jit(lambda z: form.reduced_inverse(z, (ctx, span)))(z)
    np.testing.assert_allclose(inverse @ jacobian, np.eye(flat.shape[0]), rtol=0, atol=1e-11)


def test_a_span_known_when_traced_reaches_the_root_finder_as_a_constant():
    """optimistix traces the `args` of a root find; the projected step's functions read a
    span known when the step is traced from the step instead, so that it stays a constant
    (and `uniform_span` holds inside the solve); a traced span is passed on as it is."""
    from diffrax_vi._step.projected_solve import with_known_span

    solver = dvi.CGVI(4)
    problem = problems.double_pendulum()
    ctx = solver.step_context(problem.term, 0.0, 0.1, problem.y0, problem.args)
    span = solver.formulation.span((), ctx)
    seen = []

    def inside(args):
        fixed = with_known_span(span)(args)
        seen.append(solver.formulation.uniform_span(fixed[1]))
        return fixed[1].gq.sum()

    jax.jit(inside)((ctx, span, None))
    assert seen == [True]
    traced = []
    jax.jit(lambda s: traced.append(with_known_span(s)((ctx, s, None))[1] is s) or 0.0)(span)
    assert traced == [True]


@pytest.mark.parametrize("correct", [True, False])
def test_end_on_constraint_is_the_correction_and_the_violation_there(correct):
    """`end_on_constraint` forms the momentum map's Jacobians once and gives what the two
    public functions give: for a first-order Lagrangian the end position moved onto
    `p = ϑ(q)` (with `correct`) and the distance left there; for a regular one the end state
    as it is and no violation."""
    from diffrax_vi._step.degenerate import (
        end_on_constraint,
        first_order_end_correction,
        primary_constraint_violation,
    )

    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10))
    first_order = dvi.LagrangianTerm(lambda t, q, v, args: q[0] * v[1] - 0.5 * q @ q)
    q1, p1 = jnp.array([0.3, 0.1]), jnp.array([0.02, 0.51])
    for term, regular in ((first_order, False), (problems.double_pendulum().term, True)):
        y0 = (jnp.array([0.5, 0.2]), jnp.array([0.0, 0.5]))
        ctx = solver.step_context(term, 0.0, 0.1, y0, None)
        moved, violation = jax.jit(lambda q, p: end_on_constraint(ctx, q, p, correct))(q1, p1)
        if regular:
            np.testing.assert_array_equal(np.asarray(moved), np.asarray(q1))
            assert float(violation) == 0.0
            continue
        expected = q1 + first_order_end_correction(ctx, q1, p1) if correct else q1
        np.testing.assert_allclose(np.asarray(moved), np.asarray(expected), rtol=0, atol=1e-16)
        # ϑ(q) = (0, q0): the correction takes q0 from p1[1] and leaves q1[1] alone
        np.testing.assert_allclose(np.asarray(moved), [0.51, 0.1] if correct else q1, rtol=0,
                                   atol=1e-16)
        assert float(violation) == float(primary_constraint_violation(ctx, moved, p1))
        assert float(violation) == pytest.approx(0.02 if correct else 0.21, abs=1e-15)


# every shape in float16 and float64, one in float32 (each case compiles its own programs)
@pytest.mark.parametrize("shape, dtype", [
    pytest.param(shape, dtype, marks=[pytest.mark.slow] if slow else [],
                 id=f"{'x'.join(map(str, shape))}-{jnp.dtype(dtype).name}")
    for shape, slow_dtypes in [((10, 8, 1), ()), ((18, 10, 2), (jnp.float32,)),
                               ((6, 12, 3), (jnp.float64, jnp.float32))]
    for dtype in (jnp.float64, jnp.float32, jnp.float16)
    for slow in [dtype in slow_dtypes]
])
def test_a_known_span_is_the_traced_span(dtype, shape):
    """A span known when the step is traced is computed then, in NumPy (SVDs included): the
    span a traced hidden layer gives inside a compiled step, direction by direction up to
    its sign, to the rounding of the two SVDs (LAPACK's in NumPy and in XLA), in every
    precision; the same directions live."""
    from diffrax_vi._step.span import feature_span

    k, s, d = shape  # R + 2 points, features, coordinates
    rng = np.random.default_rng(k + s + d)
    value = rng.normal(size=shape).astype(dtype)
    slope = (3 * rng.normal(size=shape)).astype(dtype)
    weights = np.asarray(dvi.GaussLegendre(k - 2).nodes_weights(dtype)[1])
    hidden = (np.ones((s, d), dtype), np.zeros((s, d), dtype))
    rtol = float(jnp.finfo(dtype).eps) ** 0.625
    known = feature_span(value, slope, weights, min(s, k - 1), rtol, hidden)
    assert all(isinstance(leaf, jax.Array) for leaf in jax.tree_util.tree_leaves(known))
    traced = jax.jit(lambda w, beta: feature_span(
        jnp.asarray(value), jnp.asarray(slope), jnp.asarray(weights), min(s, k - 1), rtol,
        (w, beta)))(*hidden)

    def directions(span):  # (D, points, k): each direction's values, slopes and ends
        return np.concatenate([np.asarray(a, np.float64) for a in (
            span.gq, span.gv, span.g0[:, None], span.gd[:, None])], axis=1)

    sign = np.sign(np.einsum("dik,dik->dk", directions(known), directions(traced)))
    assert np.all(sign != 0)
    eps = float(jnp.finfo(dtype).eps)
    for name, signs in (("gq", sign[:, None]), ("gv", sign[:, None]), ("g0", sign),
                        ("gd", sign), ("to_alpha", sign[:, None])):
        a, b = getattr(known, name), getattr(traced, name)
        assert a.dtype == b.dtype == dtype
        b = np.asarray(b, np.float64)
        np.testing.assert_allclose(np.asarray(a, np.float64) * signs, b, rtol=0,
                                   atol=128 * eps * max(1.0, float(np.max(np.abs(b)))),
                                   err_msg=name)
    np.testing.assert_array_equal(np.asarray(known.live), np.asarray(traced.live))


@pytest.mark.parametrize("activation, programs", [(dvi.tanh, 0), (dvi.gelu, 1)])
def test_a_known_span_compiles_at_most_one_program(activation, programs):
    """Computed when the step is traced, the span of a fixed hidden layer is NumPy where the
    activation has a NumPy form (tanh) and otherwise compiles one program (the features'
    values and slopes); the rest is NumPy. Evaluated by JAX operation by operation it
    compiled some 80 programs, seconds of a first call."""
    from jax.monitoring import (
        register_event_duration_secs_listener,
        unregister_event_duration_listener,
    )

    problem = problems.double_pendulum()
    solver = projected(activation, 7, 11)  # sizes that no other test compiles
    form = solver.formulation
    ctx = solver.step_context(problem.term, 0.0, 0.1, problem.y0, problem.args)
    hidden = form.hidden.parameters(solver.basis, 2, ctx.q0.dtype)
    compiles = []

    def count(event, seconds, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(seconds)

    jax.clear_caches()
    register_event_duration_secs_listener(count)
    try:
        span = form.span(hidden, ctx)
    finally:
        unregister_event_duration_listener(count)
    assert all(isinstance(leaf, jax.Array) for leaf in jax.tree_util.tree_leaves(span))
    assert len(compiles) == programs, len(compiles)
    # computed while a step is traced, it is as concrete (a constant of the compiled step)
    inside = []
    jax.make_jaxpr(lambda q: inside.append(form.span(hidden, ctx)) or q)(ctx.q0)
    for a, b in zip(jax.tree_util.tree_leaves(span), jax.tree_util.tree_leaves(inside[0]),
                    strict=True):
        assert not isinstance(b, jax.core.Tracer)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("activation", [dvi.tanh, dvi.sigmoid, jax.nn.sigmoid])
def test_numpy_features_agree_with_the_compiled_ones(activation):
    """The NumPy form of a network's features at known points (`tanh`, `sigmoid`) gives the
    values and slopes that JAX computes, to a few rounding units."""
    from diffrax_vi._step import projection

    basis = dvi.ShallowNetBasis(activation, 6)
    theta = jax.random.normal(jax.random.PRNGKey(3), (18, 2))
    nodes = dvi.GaussLegendre(5).nodes_weights_np()[0]
    taus = np.concatenate([nodes, [0.0, 1.0]])
    numpy_value, numpy_slope, _ = projection._numpy_network_features(
        theta, basis, taus, jnp.dtype(jnp.float64))
    value, slope, _ = projection._features_at(theta, basis, nodes, 2, jnp.dtype(jnp.float64))
    assert isinstance(numpy_value, np.ndarray) and numpy_value.shape == (7, 6, 2)
    np.testing.assert_allclose(numpy_value, value, rtol=0, atol=4e-16)
    w_max = float(jnp.max(jnp.abs(theta)))
    np.testing.assert_allclose(numpy_slope, slope, rtol=0, atol=4e-16 * w_max)
    assert projection._numpy_network_features(theta, dvi.ShallowNetBasis(dvi.gelu, 6), taus,
                                              jnp.dtype(jnp.float64)) is None
