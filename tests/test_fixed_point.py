"""ChordIteration: the chord iteration for the projected step, beside RoundoffNewton."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._root_finder.chord import ChordIteration
from diffrax_vi._step.projected_solve import FIRST_TRY, projected_root_find

jax.config.update("jax_enable_x64", True)

SHORT = {
    "harmonic_oscillator": (problems.harmonic_oscillator, {}, 0.5, 20),
    "kepler": (problems.kepler, dict(eccentricity=0.5), 2 * np.pi / 100, 50),
    "double_pendulum": (problems.double_pendulum, {}, 0.05, 20),
}


def network(root_finder):
    """The default NetworkVI step (tanh 10, GL8: the projected one) with `root_finder`."""
    return dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8),
                         root_finder=root_finder)


def family(name):
    return (lambda rf: dvi.CGVI(6, root_finder=rf)) if name == "cgvi" else network


def run(problem, solver, h, n, y0=None):
    ts = jnp.asarray(h * np.arange(1, n + 1))

    @eqx.filter_jit
    def go(y):
        return diffrax.diffeqsolve(
            problem.term, solver, 0.0, n * h, h, y, args=problem.args, max_steps=n,
            saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False,
        )

    return go(problem.y0 if y0 is None else y0)


def step_system(solver, problem, h):
    """The first step's projected system (context, span) and a start from uniform motion."""
    form = solver.formulation
    ctx = solver.step_context(problem.term, 0.0, h, problem.y0, problem.args)
    dim = ctx.q0.shape[0]
    if isinstance(solver.basis, dvi.ShallowNetBasis):
        hidden = form.hidden.parameters(solver.basis, dim, ctx.q0.dtype)
    else:
        hidden = jnp.zeros((solver.basis.num_params(), dim), ctx.q0.dtype)
    span = form.span(hidden, ctx)
    q0, p0 = problem.y0
    v0 = problem.term.vf(0.0, problem.y0, problem.args)[0]
    return ctx, span, form.start(lambda tau: q0 + tau * h * v0, p0, span, ctx)


@pytest.mark.parametrize("name, kind", [
    # one case of each family in `make test`, the rest in `make test-slow`
    ("kepler", "cgvi"),
    ("harmonic_oscillator", "network"),
    *(pytest.param(name, kind, marks=pytest.mark.slow) for name, kind in [
        ("harmonic_oscillator", "cgvi"), ("double_pendulum", "cgvi"),
        ("double_pendulum", "network"), ("kepler", "network")]),
])
def test_same_root_as_newton_on_a_step(name, kind):
    # Newton from uniform motion, the chord from near its root (as from the previous curve
    # continued): both run to round-off, so their step ends agree to rounding.
    make, kw, h, _ = SHORT[name]
    problem = make(**kw)
    newton = family(kind)(dvi.RoundoffNewton(ftol=0.0))
    chord = family(kind)(ChordIteration(ftol=0.0))

    @jax.jit
    def solve(y0):
        ctx, span, z0 = step_system(newton, problem, h)
        a = projected_root_find(newton.formulation, newton.solve_options, ctx, span, z0, 50)
        start = jax.tree_util.tree_map(lambda x: x * (1 + 1e-3) + 1e-4, a.value)
        b = projected_root_find(chord.formulation, chord.solve_options, ctx, span, start, 50)
        end = newton.formulation.projected_end_state
        return end(a.value, span, ctx), end(b.value, span, ctx), a.result, b.result, b.state

    ya, yb, ra, rb, state = solve(problem.y0)
    assert ra == optx.RESULTS.successful and rb == optx.RESULTS.successful
    for a, b in zip(ya, yb, strict=True):
        scale = max(1.0, float(jnp.max(jnp.abs(a))))
        assert float(jnp.max(jnp.abs(a - b))) <= 8 * 2.2e-16 * scale
    assert int(state.refreshes) == 0 and bool(state.at_floor | state.converged)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["cgvi", "network"])
def test_same_trajectory_as_newton_at_round_off(kind):
    # The whole solve, step after step, on the hardest of the three problems.
    name = "double_pendulum"
    make, kw, h, n = SHORT[name]
    problem = make(**kw)
    newton = run(problem, family(kind)(dvi.RoundoffNewton(ftol=0.0)), h, n)
    chord = run(problem, family(kind)(ChordIteration(ftol=0.0)), h, n)
    assert newton.result == diffrax.RESULTS.successful
    assert chord.result == diffrax.RESULTS.successful
    for a, b in zip(newton.ys, chord.ys, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert np.max(np.abs(a - b)) <= 1e-13 * max(1.0, np.max(np.abs(a))), name
    state = chord.solver_state
    assert int(state.iterations) >= 2 * n  # to round-off: at least two updates a step
    assert int(state.restarts) == 0


# (a chord solve's counts: test_network_oscillator_in_one_update; vmap: test_projection.py)
@pytest.mark.slow
def test_double_pendulum_trajectory_counts_and_vmap():
    # CGVI(6) with the chord run to round-off: accurate, iteration counts in the solver state
    # as for Newton, no restart; under vmap the same as a loop of single solves.
    problem = problems.double_pendulum()
    solver = dvi.CGVI(6, root_finder=ChordIteration(ftol=0.0))
    h, n = 0.05, 20

    @eqx.filter_jit
    def go(q):
        sol = diffrax.diffeqsolve(
            problem.term, solver, 0.0, n * h, h, (q, problem.y0[1]), args=problem.args,
            max_steps=n, saveat=diffrax.SaveAt(t1=True, solver_state=True), throw=False,
        )
        st = sol.solver_state
        return sol.ys[0][-1], sol.result, st.iterations, st.max_iterations, st.histogram

    starts = jnp.stack([problem.y0[0] * s for s in (1.0, 0.9, 1.1)])
    loop = [go(q) for q in starts]
    q, result, iterations, most, histogram = loop[0]
    assert result == diffrax.RESULTS.successful
    q_ref, _ = problem.reference(np.array([n * h]))
    assert np.max(np.abs(np.asarray(q) - q_ref[0])) <= 1e-10
    assert 2 * n <= int(iterations) <= 16 * n and int(most) <= 16
    assert int(np.asarray(histogram).sum()) == n
    batched = jax.vmap(go)(starts)
    assert bool(jnp.all(batched[1] == diffrax.RESULTS.successful))
    np.testing.assert_allclose(np.asarray(batched[0]), np.stack([np.asarray(o[0]) for o in loop]),
                               rtol=0, atol=1e-14)
    # (the iteration counts may differ by an update here and there: where the updates stop
    # shrinking depends on rounding, which batching changes)


@pytest.mark.parametrize("confirm, updates", [(False, 1), (True, 2)])
def test_network_oscillator_in_one_update(confirm, updates):
    # The default NetworkVI step: the oscillator's projected equations are linear, so the
    # Jacobian at the start is the Jacobian everywhere, and one chord update solves them;
    # `confirm` (the default) adds the update that removes the first one's bias.
    problem = problems.harmonic_oscillator()
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8),
                           root_finder=ChordIteration(confirm=confirm, picard=False),
                           iteration_log=10)
    sol = run(problem, solver, 0.1, 10)
    assert sol.result == diffrax.RESULTS.successful
    np.testing.assert_array_equal(np.asarray(sol.solver_state.iteration_log), updates)
    q_ref, _ = problem.reference(np.asarray(sol.ts))
    assert np.max(np.abs(np.asarray(sol.ys[0]) - q_ref)) <= 2e-14


def _stiff(root_finder, **options):
    # A stiff quartic spring at a long step: from the previous curve continued the start is
    # far, and the Jacobian there is not the one at the root.
    # At h·ω ≈ 35 its steps are far off the motion, and the energy check refuses them: off
    # here, where only the root finders are compared on the same equations.
    term = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 2500.0 * jnp.sum(q**4))
    y0 = (jnp.array([1.0]), jnp.array([0.0]))
    options.setdefault("energy_check", False)
    sol = diffrax.diffeqsolve(
        term, dvi.CGVI(6, root_finder=root_finder, **options), 0.0, 2.0, 0.2, y0,
        max_steps=10, saveat=diffrax.SaveAt(t1=True), throw=False,
    )
    return sol.result, sol.ys[0][-1]


def test_fails_loudly_where_the_chord_cannot_contract():
    # Without a second try (an iteration cap within the first), the step must fail, not be
    # accepted wrong.
    result, _ = _stiff(ChordIteration(ftol=1.0), root_find_max_steps=FIRST_TRY)
    assert result != diffrax.RESULTS.successful


@pytest.mark.slow
def test_a_failed_first_try_goes_on_with_newton():
    # Where the chord iteration cannot contract from the previous curve, the restart from the
    # trajectory seed goes on with refreshed Jacobians: the step is Newton's.
    newton, q_newton = _stiff(dvi.RoundoffNewton(ftol=1.0, restart=True))
    assert newton == diffrax.RESULTS.successful
    for rf in (ChordIteration(ftol=1.0, restart=True),
               ChordIteration(ftol=0.0, predict=True, restart=True)):
        result, q = _stiff(rf)
        assert result == diffrax.RESULTS.successful
        np.testing.assert_allclose(np.asarray(q), np.asarray(q_newton), atol=1e-10)


@pytest.mark.slow
def test_refresh_solves_where_the_chord_fails():
    newton, q_newton = _stiff(dvi.RoundoffNewton(ftol=1.0, restart=True))
    refreshing, q_refreshing = _stiff(ChordIteration(ftol=1.0, refresh=0.5))
    assert newton == diffrax.RESULTS.successful
    assert refreshing == diffrax.RESULTS.successful
    np.testing.assert_allclose(np.asarray(q_refreshing), np.asarray(q_newton), atol=1e-10)


def test_refresh_speeds_up_a_slow_chord_on_a_step():
    # The double pendulum's first step at h = 0.5 from uniform motion: the chord contracts
    # slowly (about 20 updates to round-off); refreshing the Jacobian where an update shrinks
    # by less than 10x turns it into Newton's method.
    problem = problems.double_pendulum()

    @jax.jit
    def solve(y0):
        out = []
        for rf in (ChordIteration(ftol=0.0), ChordIteration(ftol=0.0, refresh=0.1)):
            solver = dvi.CGVI(6, root_finder=rf)
            ctx, span, z0 = step_system(solver, problem, 0.5)
            sol = projected_root_find(solver.formulation, solver.solve_options, ctx, span, z0, 100)
            out.append((sol.value, sol.result, sol.stats["num_steps"], sol.state.refreshes))
        return out

    (plain, r_plain, n_plain, _), (fast, r_fast, n_fast, refreshes) = solve(problem.y0)
    assert r_plain == r_fast == optx.RESULTS.successful
    assert int(n_fast) < int(n_plain) and int(refreshes) >= 1
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(plain),
                    strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)


def _system(z, args):
    # A small smooth nonlinear system with the root (1, 2): the root finder on its own,
    # with the Jacobian by jax.jacfwd (no "jacobian" option).
    x, y = z[0], z[1]
    return jnp.stack([x**2 + 0.1 * jnp.sin(y) - 1 - 0.1 * jnp.sin(2.0), y + 0.2 * x**3 - 2.2])


@pytest.mark.parametrize("inverse", [True, False])
@pytest.mark.parametrize("refresh", [None, 0.5])
def test_root_finder_on_its_own(inverse, refresh):
    rf = ChordIteration(ftol=0.0, inverse=inverse, refresh=refresh)
    sol = optx.root_find(_system, rf, jnp.array([1.1, 1.9]), max_steps=50, throw=False)
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(sol.value), [1.0, 2.0], rtol=0, atol=4e-16)
    assert int(sol.stats["num_steps"]) >= 3  # linear convergence, then the floor rule
    assert int(sol.state.refreshes) == 0  # the start is close: no refresh needed
    eps = float(jnp.finfo(jnp.float64).eps)
    assert float(jnp.max(jnp.abs(sol.state.f))) <= 4 * eps


def test_divergence_and_non_finite_are_reported():
    rf = ChordIteration()
    # arctan from beyond its turning region: the chord overshoots further on every update
    sol = optx.root_find(lambda z, a: jnp.arctan(z), rf, jnp.array([1.5]), max_steps=50,
                         throw=False)
    assert sol.result == optx.RESULTS.nonlinear_divergence
    # a Jacobian singular at the start: the first update is not finite
    sol = optx.root_find(lambda z, a: z**3 - 1, rf, jnp.array([0.0]), max_steps=20, throw=False)
    assert sol.result == optx.RESULTS.nonfinite


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float16])
@pytest.mark.parametrize("inverse, predict", [(True, False), (False, False), (True, True)])
def test_low_precision_stays_in_its_dtype(dtype, inverse, predict):
    # Below 32 bits the factorisation runs in float32; the iterates keep the working dtype.
    rf = ChordIteration(ftol=0.0, inverse=inverse, predict=predict)
    sol = optx.root_find(_system, rf, jnp.array([1.1, 1.9], dtype), max_steps=50, throw=False)
    assert sol.value.dtype == dtype and sol.state.f.dtype == dtype
    assert sol.result == optx.RESULTS.successful
    eps = float(jnp.finfo(dtype).eps)
    np.testing.assert_allclose(np.asarray(sol.value, np.float64), [1.0, 2.0], atol=8 * eps)


def test_is_accepted_where_newton_is_and_checks_its_settings():
    rf = ChordIteration(ftol=0.0)
    assert isinstance(rf, dvi.RoundoffNewton)
    solver = network(rf)
    assert isinstance(solver.formulation, dvi.VariableProjection)
    assert solver.root_finder is rf
    assert dvi.CGVI(6, root_finder=rf).root_finder is rf
    with pytest.raises(ValueError, match="refresh"):
        ChordIteration(refresh=1.5)
    with pytest.raises(ValueError, match="refresh"):
        ChordIteration(refresh=0)
    with pytest.raises(TypeError, match="inverse"):
        ChordIteration(inverse=1)
    with pytest.raises(TypeError, match="predict"):
        ChordIteration(predict="yes")
    with pytest.raises(TypeError, match="pivoted_fallback"):
        ChordIteration(pivoted_fallback=1)
    with pytest.raises(ValueError, match="ftol"):  # the parent's checks still run
        ChordIteration(ftol=-1)


# -- round-off by prediction ---------------------------------------------------------------------
@pytest.mark.parametrize("name", [
    "harmonic_oscillator", *(pytest.param(n, marks=pytest.mark.slow) for n in list(SHORT)[1:])])
def test_predict_reaches_round_off_in_fewer_updates(name):
    # From a start 1e-3 off the root (as in the test against Newton above): the prediction
    # ends where the updates would stop shrinking, to rounding, with fewer of them.
    make, kw, h, _ = SHORT[name]
    problem = make(**kw)
    newton = dvi.CGVI(6, root_finder=dvi.RoundoffNewton(ftol=0.0))

    @jax.jit
    def solve(y0):
        ctx, span, z0 = step_system(newton, problem, h)
        a = projected_root_find(newton.formulation, newton.solve_options, ctx, span, z0, 50)
        start = jax.tree_util.tree_map(lambda x: x * (1 + 1e-3) + 1e-4, a.value)
        out = []
        for predict in (False, True):
            solver = dvi.CGVI(6, root_finder=ChordIteration(ftol=0.0, predict=predict))
            sol = projected_root_find(solver.formulation, solver.solve_options, ctx, span,
                                      start, 50)
            out.append((newton.formulation.projected_end_state(sol.value, span, ctx),
                        sol.result, sol.stats["num_steps"]))
        return newton.formulation.projected_end_state(a.value, span, ctx), out

    ya, ((y_full, r_full, n_full), (y_pred, r_pred, n_pred)) = solve(problem.y0)
    assert r_full == optx.RESULTS.successful and r_pred == optx.RESULTS.successful
    for a, b in zip(ya, y_pred, strict=True):
        scale = max(1.0, float(jnp.max(jnp.abs(a))))
        assert float(jnp.max(jnp.abs(a - b))) <= 8 * 2.2e-16 * scale
    assert int(n_pred) < int(n_full)


@pytest.mark.slow  # the prediction's claim, on a step: test_predict_reaches_round_off_...
def test_predict_halves_the_updates_of_a_run_to_round_off():
    # Kepler e = 0.5, 100 steps per orbit: chord to round-off in 2 updates a step (4.5
    # without the prediction, on the benchmarks page), ending where it does without it.
    make, kw, h, n = SHORT["kepler"]
    problem = make(**kw)
    ends, histograms = [], []
    for predict in (False, True):
        # the chord iteration itself (not the Jacobian-free one this Lagrangian allows)
        solver = dvi.CGVI(6, root_finder=ChordIteration(ftol=0.0, inverse=False,
                                                             predict=predict, picard=False))
        sol = run(problem, solver, h, n)
        assert sol.result == diffrax.RESULTS.successful
        ends.append(np.asarray(sol.ys[0][-1]))
        histograms.append(np.asarray(sol.solver_state.histogram))
    # every step after the first (which starts from the constant curve) in two updates, and
    # at most half the updates of the run without the prediction
    assert histograms[1][:3].sum() >= n - 1, histograms[1][:8]
    updates = [int(np.dot(np.arange(hist.size), hist)) for hist in histograms]
    assert updates[1] <= 0.5 * updates[0], updates
    np.testing.assert_allclose(ends[1], ends[0], rtol=0, atol=1e-13)


# -- the kinetic matrix ---------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["cgvi", "network"])
@pytest.mark.parametrize("uniform", [True, False])
def test_kinetic_inverse_is_the_jacobian_inverse_without_forces(kind, uniform):
    mass = jnp.array([[2.0, 0.3], [0.3, 1.0]])
    term = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ mass @ v)
    y0 = (jnp.array([0.3, -0.2]), jnp.array([0.5, 0.1]))
    solver = family(kind)(ChordIteration(matrix="kinetic"))
    form = solver.formulation
    dim = 2
    ctx = solver.step_context(term, 0.0, 0.25, y0, None)
    if isinstance(solver.basis, dvi.ShallowNetBasis):
        hidden = form.hidden.parameters(solver.basis, dim, jnp.float64)
    else:
        hidden = jnp.zeros((solver.basis.num_params(), dim), jnp.float64)
    span = form.span(hidden, ctx)
    assert form.uniform_span(span)  # one span in every coordinate, known at trace time
    k = span.gq.shape[2]
    rng = np.random.default_rng(0)
    z = (jnp.asarray(rng.normal(size=(k, dim))) * span.live, jnp.asarray(rng.normal(size=dim)))
    f = (jnp.asarray(rng.normal(size=(k, dim))) * span.live, jnp.asarray(rng.normal(size=dim)))

    @jax.jit  # one program, not one per JAX operation; the span a constant, as in a step
    def both(z, f):
        inverse = form.kinetic_inverse(z, (ctx, span), uniform=uniform)
        jac = form.reduced_jacobian(z, (ctx, span))
        flat_f, _ = jax.flatten_util.ravel_pytree(f)
        return jax.flatten_util.ravel_pytree(inverse(f))[0], jnp.linalg.solve(jac, flat_f)

    got, expected = both(z, f)
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=0,
                               atol=1e-11 * float(jnp.max(jnp.abs(expected))))


@pytest.mark.parametrize("name", [
    "harmonic_oscillator", *(pytest.param(n, marks=pytest.mark.slow) for n in list(SHORT)[1:])])
def test_kinetic_iteration_reaches_newtons_trajectory(name):
    make, kw, h, n = SHORT[name]
    problem = make(**kw)
    newton = run(problem, dvi.CGVI(6, root_finder=dvi.RoundoffNewton(ftol=0.0)), h, n)
    kinetic = run(problem, dvi.CGVI(6, root_finder=ChordIteration(ftol=0.0,
                                                                       matrix="kinetic")), h, n)
    assert kinetic.result == diffrax.RESULTS.successful
    for a, b in zip(newton.ys, kinetic.ys, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert np.max(np.abs(a - b)) <= 1e-13 * max(1.0, np.max(np.abs(a))), name
    state = kinetic.solver_state
    assert int(state.restarts) == 0
    # linear convergence at a rate of order (hω)²: more updates than Newton, but bounded
    assert 2 * n <= int(state.iterations) <= 20 * n


@pytest.mark.slow
def test_kinetic_iteration_on_the_outer_solar_system():
    # 18 coordinates at h = 500 days: the chord iteration's 162-square Jacobian costs more
    # than all of the kinetic iteration's updates (see the benchmarks page).
    problem = problems.outer_solar_system(dtype=jnp.float64)
    h, n = 500.0, 10
    newton = run(problem, dvi.CGVI(7, root_finder=dvi.RoundoffNewton(ftol=0.0)), h, n)
    kinetic = run(problem, dvi.CGVI(7, root_finder=ChordIteration(
        ftol=0.0, matrix="kinetic")), h, n)
    assert kinetic.result == diffrax.RESULTS.successful
    a, b = np.asarray(newton.ys[0]), np.asarray(kinetic.ys[0])
    assert np.max(np.abs(a - b)) <= 1e-13 * np.max(np.abs(a))


@pytest.mark.slow  # the kinetic solve: test_kinetic_iteration_reaches_newtons_trajectory
def test_kinetic_iteration_with_a_network_and_under_vmap():
    problem = problems.double_pendulum()
    solver = network(ChordIteration(ftol=0.0, matrix="kinetic"))
    h, n = 0.05, 10

    @eqx.filter_jit
    def go(q):
        sol = diffrax.diffeqsolve(
            problem.term, solver, 0.0, n * h, h, (q, problem.y0[1]), args=problem.args,
            max_steps=n, saveat=diffrax.SaveAt(t1=True), throw=False,
        )
        return sol.ys[0][-1], sol.result

    starts = jnp.stack([problem.y0[0] * s for s in (1.0, 0.9)])
    loop = [go(q) for q in starts]
    assert all(r == diffrax.RESULTS.successful for _, r in loop)
    q_ref, _ = problem.reference(np.array([n * h]))
    assert np.max(np.abs(np.asarray(loop[0][0]) - q_ref[0])) <= 1e-10
    batched = jax.vmap(go)(starts)
    np.testing.assert_allclose(np.asarray(batched[0]), np.stack([np.asarray(o[0]) for o in loop]),
                               rtol=0, atol=1e-14)


# (a loud failure: test_kinetic_iteration_refuses_a_degenerate_lagrangian_loudly; the refresh:
# test_refresh_speeds_up_a_slow_chord_on_a_step)
@pytest.mark.slow
def test_kinetic_iteration_fails_loudly_or_refreshes():
    # The stiff spring: the kinetic matrix cannot see the force's stiffness. Without a
    # refresh the step fails; with one, the iteration turns into Newton's and solves it.
    result, _ = _stiff(ChordIteration(ftol=1.0, matrix="kinetic"))
    assert result != diffrax.RESULTS.successful
    newton, q_newton = _stiff(dvi.RoundoffNewton(ftol=1.0, restart=True))
    refreshing, q_refreshing = _stiff(ChordIteration(ftol=1.0, matrix="kinetic",
                                                          refresh=0.5, restart=True))
    assert refreshing == diffrax.RESULTS.successful
    np.testing.assert_allclose(np.asarray(q_refreshing), np.asarray(q_newton), atol=1e-10)


def test_kinetic_iteration_refuses_a_degenerate_lagrangian_loudly():
    # L linear in v has no mass matrix: the kinetic matrix is singular and the step fails.
    term = dvi.LagrangianTerm(lambda t, q, v, args: q[0] * v[1] - 0.5 * q @ q)
    y0 = (jnp.array([0.5, 0.2]), jnp.array([0.0, 0.5]))
    sol = diffrax.diffeqsolve(
        term, dvi.CGVI(4, root_finder=ChordIteration(matrix="kinetic")), 0.0, 0.3, 0.1,
        y0, max_steps=5, throw=False,
    )
    assert sol.result != diffrax.RESULTS.successful


def test_kinetic_matrix_needs_the_projected_step():
    with pytest.raises(ValueError, match="matrix"):
        ChordIteration(matrix="mass")
    rf = ChordIteration(matrix="kinetic")
    with pytest.raises(ValueError, match="kinetic"):
        optx.root_find(_system, rf, jnp.array([1.1, 1.9]), max_steps=5, throw=False)


@pytest.mark.parametrize("dtype", [pytest.param(jnp.float32, marks=pytest.mark.slow), jnp.float16])
def test_kinetic_iteration_stays_in_its_dtype(dtype):
    problem = problems.harmonic_oscillator(dtype=dtype)
    solver = dvi.CGVI(4, root_finder=ChordIteration(matrix="kinetic"))
    t0, t1, dt = (jnp.asarray(x, dtype) for x in (0.0, 2.0, 0.25))  # times in the state's dtype
    sol = diffrax.diffeqsolve(problem.term, solver, t0, t1, dt, problem.y0,
                              args=problem.args, max_steps=8, throw=False)
    assert sol.result == diffrax.RESULTS.successful
    assert sol.ys[0].dtype == dtype and sol.ys[1].dtype == dtype
    q_ref, _ = problem.reference(np.array([2.0]))
    eps = float(jnp.finfo(dtype).eps)
    assert np.max(np.abs(np.asarray(sol.ys[0][-1], np.float64) - q_ref[0])) <= 64 * eps


def test_confirm_is_checked_and_inherited():
    assert dvi.RoundoffNewton().confirm and ChordIteration().confirm
    assert not dvi.RoundoffNewton(confirm=False).confirm
    for cls in (dvi.RoundoffNewton, ChordIteration):
        with pytest.raises(TypeError, match="confirm"):
            cls(confirm=1)
    # the network's default root finder does not confirm; CGVI's does
    assert not network(None).root_finder.confirm
    assert dvi.CGVI(6).root_finder.confirm


@pytest.mark.parametrize("root_finder", [dvi.RoundoffNewton(ftol=1.0),
                                         ChordIteration(ftol=0.0, predict=True)])
def test_a_non_finite_start_ends_the_solve_at_once(root_finder):
    # Run as one whole solve (the solver's hints), a start whose residual is not finite is
    # reported as such, with no update made: it neither loops to the cap nor passes.
    solver = dvi.CGVI(6, root_finder=root_finder)
    ctx, span, z0 = step_system(solver, problems.harmonic_oscillator(), 0.5)
    bad = jax.tree_util.tree_map(lambda a: a.at[(0,) * a.ndim].set(jnp.nan), z0)
    # one compiled program for both starts (op by op, the solve compiled some 80 programs)
    run = eqx.filter_jit(lambda z: projected_root_find(
        solver.formulation, solver.solve_options, ctx, span, z, 50))
    sol = run(bad)
    assert sol.result == optx.RESULTS.nonfinite
    assert int(sol.stats["num_steps"]) == 0
    good = run(z0)
    assert good.result == optx.RESULTS.successful and int(good.stats["num_steps"]) >= 1


@pytest.mark.parametrize("newton", [False, True])
@pytest.mark.parametrize("given, fallback", [("exact", False), ("non-finite", False),
                                             ("non-finite", True)])
def test_the_hint_inverse_starts_the_iteration(given, fallback, newton):
    """The hint `inverse` (the formulation's own inverse of the Jacobian) replaces the
    factorisation at the start of the chord iteration and in every Newton update; where it
    is not finite (a vanished pivot), the solve fails, or with
    `pivoted_fallback` the pivoted factorisation takes over and the solve ends at the same
    root."""
    from diffrax_vi._root_finder.step_hints import StepHints, step_options

    used = []

    def inverse(jac, z, args):
        used.append(True)
        assert jac.shape == (2, 2)  # the Jacobian the root finder formed at `z`
        exact = jnp.linalg.inv(jac)
        return exact if given == "exact" else exact * jnp.nan

    rf = (dvi.RoundoffNewton(ftol=0.0, pivoted_fallback=fallback) if newton
          else ChordIteration(ftol=0.0, predict=True, pivoted_fallback=fallback))
    options = step_options(StepHints(inverse=inverse, max_iterations=50))
    sol = optx.root_find(_system, rf, jnp.array([1.1, 1.9]), options=options, max_steps=50,
                         throw=False)
    if given == "non-finite" and not fallback:
        # the chord's update is not finite; Newton's line search finds no decrease along it
        failed = optx.RESULTS.nonlinear_divergence if newton else optx.RESULTS.nonfinite
        assert used and sol.result == failed
        return
    assert used and sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(sol.value), [1.0, 2.0], rtol=0, atol=4e-16)
    if not newton:
        assert bool(jnp.all(jnp.isfinite(sol.state.factors[0])))


@pytest.mark.parametrize("dtype", [pytest.param(jnp.float32, marks=pytest.mark.slow), jnp.float16])
def test_default_cgvi_on_two_coordinates_stays_in_its_dtype(dtype):
    """The default step's start on two coordinates (the Jacobian as one product, the inverse
    by elimination, which runs in float32 below 32 bits) keeps the state in its dtype and
    ends near the float64 run."""
    term = dvi.LagrangianTerm(
        lambda t, q, v, args: 0.5 * v @ v - 0.5 * q @ q - 0.1 * q[0] ** 2 * q[1])

    def run(dtype):
        y0 = (jnp.array([0.5, 0.2], dtype), jnp.array([0.0, 0.3], dtype))
        t0, t1, dt = (jnp.asarray(x, dtype) for x in (0.0, 2.0, 0.25))
        return diffrax.diffeqsolve(term, dvi.CGVI(4), t0, t1, dt, y0, max_steps=8,
                                   throw=False)

    sol, ref = run(dtype), run(jnp.float64)
    assert sol.result == diffrax.RESULTS.successful
    assert sol.ys[0].dtype == dtype and sol.ys[1].dtype == dtype
    eps = float(jnp.finfo(dtype).eps)
    np.testing.assert_allclose(np.asarray(sol.ys[0], np.float64), np.asarray(ref.ys[0]),
                               rtol=0, atol=16 * eps)


@pytest.mark.parametrize("earlier, stops", [(1e-5, True), (0.5, False), (0.0, False)])
def test_predict_stops_at_an_update_that_is_rounding_noise(earlier, stops):
    # The iteration stands one rounding unit from F(z) = z - 1 + 1e-20 (identity matrix; the
    # 1e-20, lost when z is rounded, keeps the residual off zero, so `ftol=0` cannot end it),
    # after an update of 5e-14 that had contracted by `earlier`. The next update is rounding
    # noise: its ratio to the one before (4e-3) is not the rate; what is left is `earlier`
    # times the noise. A fast rate (1e-5) ends the solve there; a slow one, or none known
    # (the first update), does not.
    rf = ChordIteration(ftol=0.0, predict=True)
    eps = float(jnp.finfo(jnp.float64).eps)
    y = jnp.array([1.0 + eps, 0.5])

    def fn(z, args):
        return z - jnp.array([1.0, 0.5]) + 1e-20, None

    state = rf.init(fn, y, None, {}, None, None, frozenset())
    state = eqx.tree_at(lambda s: (s.step_norm, s.contraction), state,
                        (jnp.asarray(5e-14), jnp.asarray(earlier)))
    new, state, _ = rf._update(fn, y, None, {}, state)
    np.testing.assert_array_equal(new, [1.0, 0.5])
    assert bool(state.converged) is stops


# -- the loop's carry ------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_loop_layout_packs_and_restores_the_state_exactly(dtype):
    from diffrax_vi._root_finder.newton import _LoopLayout

    rf = ChordIteration(ftol=0.0, predict=True)
    state = rf.init(lambda z, a: (z * z - 2, None), jnp.ones(3, dtype), None, {}, None, None,
                    frozenset())
    state = eqx.tree_at(lambda s: (s.step_norm, s.contraction, s.stalls, s.iterations,
                                   s.at_floor),
                        state, (jnp.asarray(3e-4, dtype), jnp.asarray(0.125, dtype),
                                jnp.asarray(2, jnp.int32), jnp.asarray(4099, jnp.int32),
                                jnp.array(True)))
    layout = _LoopLayout.of(state, rf._loop_constants())
    rest, packed = layout.pack(state)
    # the scalars that change ride as one vector (float32 at least); the matrix stays out
    assert packed.ndim == 1 and packed.dtype == jnp.result_type(jnp.float32, dtype)
    assert all(leaf.ndim == 1 for leaf in rest)  # only the residual
    back = layout.unpack(rest, packed)
    for a, b in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(back),
                    strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("refresh", [None, 0.5])
def test_loop_constants_are_what_an_update_leaves_alone(refresh):
    rf = ChordIteration(ftol=0.0, refresh=refresh)

    def fn(z, args):
        return z * z * z - jnp.array([2.0, 3.0]), None

    y = jnp.array([1.5, 1.0])
    state = rf.init(fn, y, None, {}, None, None, frozenset())
    _, after, _ = rf._update(fn, y, None, {}, state)
    for name in rf._loop_constants():
        for a, b in zip(jax.tree_util.tree_leaves(getattr(state, name)),
                        jax.tree_util.tree_leaves(getattr(after, name)), strict=True):
            np.testing.assert_array_equal(a, b)
