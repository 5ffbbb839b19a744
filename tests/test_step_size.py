"""RetryFailedSteps: constant steps, a failed one split into pieces instead of ending the run."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems

# The all-parameter step: it fails now and then at h = 3 on the oscillator, whose linear
# equations the default (projected) step solves at any step length.
NETWORK = dvi.NetworkVI(
    dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8), formulation=dvi.FreeEndpoints()
)


@eqx.filter_jit
def _run(controller, h, steps):
    """One compilation per controller: the step and the span are traced."""
    problem = problems.harmonic_oscillator(dtype=jnp.float64)
    return diffrax.diffeqsolve(
        problem.term, NETWORK, 0.0, steps * h, h, problem.y0, stepsize_controller=controller,
        saveat=diffrax.SaveAt(steps=True, solver_state=True), throw=False, max_steps=64,
    )


def _solve(controller, h, steps):
    return _run(controller, jnp.asarray(h), jnp.asarray(float(steps)))


def _kept(sol):
    n = int(sol.stats["num_accepted_steps"])
    return np.asarray(sol.ts)[:n], np.asarray(sol.ys[0])[:n, 0]


def test_without_failures_it_takes_the_constant_steps_exactly():
    """No failed step: the same times and the same numbers as ConstantStepSize, bit for bit."""
    fixed = _solve(diffrax.ConstantStepSize(), 0.5, 6)
    retry = _solve(dvi.RetryFailedSteps(), 0.5, 6)
    assert fixed.result == diffrax.RESULTS.successful
    assert retry.result == diffrax.RESULTS.successful
    assert int(retry.stats["num_rejected_steps"]) == 0
    (ts_f, q_f), (ts_r, q_r) = _kept(fixed), _kept(retry)
    np.testing.assert_array_equal(ts_r, ts_f)
    np.testing.assert_array_equal(q_r, q_f)


def test_a_failed_step_is_split_and_the_run_goes_on():
    """Steps of h = 3 fail on the oscillator now and then (ConstantStepSize ends there); the
    retry splits those intervals, keeps every grid point, and stays accurate."""
    h, steps = 3.0, 8
    fixed = _solve(diffrax.ConstantStepSize(), h, steps)
    assert fixed.result != diffrax.RESULTS.successful
    retry = _solve(dvi.RetryFailedSteps(), h, steps)
    assert retry.result == diffrax.RESULTS.successful
    rejected = int(retry.stats["num_rejected_steps"])
    assert rejected > 0
    ts, q = _kept(retry)
    assert ts[-1] == steps * h
    grid = h * np.arange(1, steps + 1)
    assert set(grid) <= set(ts)  # every grid point is a step end, exactly
    # each failed trial was replaced by pieces of half its length
    assert len(ts) == steps + rejected
    assert np.all(np.isin(np.round(np.diff(np.concatenate([[0.0], ts])), 12), [h, h / 2]))
    problem = problems.harmonic_oscillator(dtype=jnp.float64)
    q_ref, _ = problem.reference(ts)
    assert np.max(np.abs(q - q_ref[:, 0])) < 1e-6
    p = np.asarray(retry.ys[1])[: len(ts), 0]
    energy = jax.vmap(lambda a, b: problem.energy(0.0, a, b))(
        jnp.asarray(q)[:, None], jnp.asarray(p)[:, None])
    e0 = problem.energy(0.0, *problem.y0)
    assert float(jnp.max(jnp.abs(energy - e0)) / jnp.abs(e0)) < 1e-7


def test_when_the_smallest_piece_fails_the_solvers_failure_stands():
    """`max_splits=0`: nothing is retried, and the run ends with the solver's own result and
    report at the same step as under ConstantStepSize."""
    h, steps = 3.0, 8
    fixed = _solve(diffrax.ConstantStepSize(), h, steps)
    once = _solve(dvi.RetryFailedSteps(max_splits=0), h, steps)
    assert once.result == fixed.result != diffrax.RESULTS.successful
    assert float(once.solver_state.report.t) == float(fixed.solver_state.report.t)
    assert dvi.failure_kind(once.result) == dvi.failure_kind(fixed.result) == "stalled"


def _sqrt_decay(solver, controller, t1, h, y0=1.0, **kwargs):
    """y' = -sqrt(y): a Runge–Kutta stage that overshoots below zero makes the step NaN.
    The NaN is a constant branch of a `where` (and the square root sees only positive
    numbers), so that a rejected trial adds nothing but zeros to a gradient."""

    def field(t, y, args):
        positive = y > 0
        return jnp.where(positive, -jnp.sqrt(jnp.where(positive, y, 1.0)), jnp.nan)

    term = diffrax.ODETerm(field)
    return diffrax.diffeqsolve(
        term, solver, 0.0, t1, h, jnp.asarray(y0), stepsize_controller=controller,
        saveat=diffrax.SaveAt(t1=True), throw=False, max_steps=400, **kwargs
    )


def test_any_solver_whose_failed_step_is_not_finite():
    """Tsit5 on y' = -sqrt(y): a full step near y = 0 gives NaN; its pieces do not."""
    fixed = _sqrt_decay(diffrax.Tsit5(), diffrax.ConstantStepSize(), 1.9, 0.475)
    assert np.isnan(fixed.ys).all()  # diffrax accepts the NaN step: the run ends in NaN
    retry = _sqrt_decay(diffrax.Tsit5(), dvi.RetryFailedSteps(), 1.9, 0.475)
    assert retry.result == diffrax.RESULTS.successful
    assert int(retry.stats["num_rejected_steps"]) > 0
    np.testing.assert_allclose(float(retry.ys[0]), (1 - 1.9 / 2) ** 2, atol=1e-4)


def test_under_vmap_each_member_retries_on_its_own():
    """Under vmap one member splits failed steps, the other takes plain steps; each gives
    what it gives alone."""
    y0s = jnp.array([1.0, 9.0])
    batch = jax.vmap(
        lambda y0: _sqrt_decay(diffrax.Tsit5(), dvi.RetryFailedSteps(), 1.9, 0.475, y0=y0)
    )(y0s)
    assert np.all(np.asarray(batch.result == diffrax.RESULTS.successful))
    rejected = np.asarray(batch.stats["num_rejected_steps"])
    assert rejected[0] > 0 and rejected[1] == 0  # y0 = 9 stays clear of zero
    for k, y0 in enumerate(y0s):
        one = _sqrt_decay(diffrax.Tsit5(), dvi.RetryFailedSteps(), 1.9, 0.475, y0=y0)
        assert one.result == diffrax.RESULTS.successful
        np.testing.assert_allclose(batch.ys[k], one.ys, rtol=1e-12)


def test_backwards_in_time_and_an_open_end_match_constant_steps():
    """t1 < t0, and t1 = inf with an event: the same steps as ConstantStepSize."""
    term = diffrax.ODETerm(lambda t, y, args: -y)
    for controller in (diffrax.ConstantStepSize(), dvi.RetryFailedSteps()):
        back = diffrax.diffeqsolve(term, diffrax.Tsit5(), 1.0, 0.0, -0.1, jnp.asarray(1.0),
                                   stepsize_controller=controller,
                                   saveat=diffrax.SaveAt(steps=True), max_steps=20)
        event = diffrax.Event(lambda t, y, args, **kw: y - 0.3)
        open_end = diffrax.diffeqsolve(term, diffrax.Tsit5(), 0.0, jnp.inf, 0.1,
                                       jnp.asarray(1.0), stepsize_controller=controller,
                                       event=event, max_steps=40)
        if isinstance(controller, diffrax.ConstantStepSize):
            expected = (back.ts, back.ys, open_end.ts, open_end.ys)
        else:
            for a, b in zip((back.ts, back.ys, open_end.ts, open_end.ys), expected,
                            strict=True):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(expected[2][0]) == pytest.approx(np.log(1 / 0.3), abs=0.1)


def test_jit_compiles_once_for_all_step_sizes():
    runs = []

    @eqx.filter_jit
    def run(h):
        runs.append(1)
        return _sqrt_decay(diffrax.Tsit5(), dvi.RetryFailedSteps(), 1.9, h)

    for h in (0.475, 0.2375):
        assert run(jnp.asarray(h)).result == diffrax.RESULTS.successful
    assert len(runs) == 1


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(shrink=0.0), "shrink must be a number in \\(0, 1\\)"),
        (dict(shrink=1.0), "shrink must be a number in \\(0, 1\\)"),
        (dict(shrink=True), "shrink must be a number in \\(0, 1\\)"),
        (dict(shrink="half"), "shrink must be a number in \\(0, 1\\)"),
        (dict(max_splits=-1), "max_splits must be a non-negative integer"),
        (dict(max_splits=2.5), "max_splits must be a non-negative integer"),
        (dict(max_splits=True), "max_splits must be a non-negative integer"),
    ],
)
def test_bad_arguments_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        dvi.RetryFailedSteps(**kwargs)


def test_a_missing_step_is_named():
    term = diffrax.ODETerm(lambda t, y, args: -y)
    with pytest.raises(ValueError, match="RetryFailedSteps needs the step: pass dt0"):
        diffrax.diffeqsolve(term, diffrax.Tsit5(), 0.0, 1.0, None, jnp.asarray(1.0),
                            stepsize_controller=dvi.RetryFailedSteps())


def test_gradients_flow_through_a_run_with_retries():
    """Reverse mode through a solve whose failed steps were split matches central
    differences (Tsit5 on the guarded y' = -sqrt(y): a rejected trial adds only zeros)."""

    def tsit5_final(y0):
        return _sqrt_decay(diffrax.Tsit5(), dvi.RetryFailedSteps(), 1.9, 0.475, y0=y0).ys[0]

    y0, step = jnp.asarray(1.0), 1e-6
    central = (tsit5_final(y0 + step) - tsit5_final(y0 - step)) / (2 * step)
    np.testing.assert_allclose(float(jax.grad(tsit5_final)(y0)), float(central), rtol=1e-6)


@pytest.mark.long
def test_gradients_through_networkvi_with_retried_steps():
    """NetworkVI on the oscillator at h = 3 with retried steps: reverse mode against central
    differences (the failed trials' NaN end states are constants, so they add nothing).
    About a minute of compilation, so it runs in `make test-long`."""
    problem = problems.harmonic_oscillator(dtype=jnp.float64)

    @eqx.filter_jit
    def network_final(q0):
        sol = diffrax.diffeqsolve(
            problem.term, NETWORK, 0.0, 12.0, 3.0, (q0, problem.y0[1]),
            stepsize_controller=dvi.RetryFailedSteps(), saveat=diffrax.SaveAt(t1=True),
            throw=False, max_steps=32,
        )
        return sol.ys[0][0, 0], sol.stats["num_rejected_steps"]

    q0 = problem.y0[0]
    value, rejected = network_final(q0)
    assert int(rejected) > 0 and np.isfinite(float(value))
    grad = jax.grad(lambda q: network_final(q)[0])(q0)
    step = 1e-6
    central = (network_final(q0 + step)[0] - network_final(q0 - step)[0]) / (2 * step)
    # the root finds stop at their residual floor, which limits the central difference
    np.testing.assert_allclose(np.asarray(grad)[0], float(central), rtol=1e-3)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float16])
def test_reduced_precision_times_and_states_keep_their_dtype(dtype):
    term = diffrax.ODETerm(
        lambda t, y, args: jnp.where(y > 0, -jnp.sqrt(jnp.where(y > 0, y, 1.0)), jnp.nan)
    )
    sol = diffrax.diffeqsolve(
        term, diffrax.Tsit5(), dtype(0.0), dtype(1.9), dtype(0.475), jnp.asarray(1.0, dtype),
        stepsize_controller=dvi.RetryFailedSteps(), saveat=diffrax.SaveAt(steps=True),
        throw=False, max_steps=64,
    )
    assert sol.result == diffrax.RESULTS.successful
    assert int(sol.stats["num_rejected_steps"]) > 0
    assert sol.ts.dtype == dtype and sol.ys.dtype == dtype
