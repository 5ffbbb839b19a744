"""Loud failures: every way a step's nonlinear solve can fail ends `diffeqsolve` with its own
`diffrax.RESULTS` member, keeps the accepted steps, and says where and why it failed."""

from functools import partial

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._results import STEP_FAILURES
from tests.helpers import motionless_cgvi

TS = jnp.linspace(0.0, 0.3, 4)


def run(solver, term, y0, *, throw=False, args=None):
    return diffrax.diffeqsolve(
        term, solver, 0.0, 0.3, 0.1, y0, args=args,
        saveat=diffrax.SaveAt(ts=TS, solver_state=True), throw=throw,
    )  # fmt: skip


cheap = partial(motionless_cgvi, 3, 4)


def rootless():
    """A degenerate system without a root: momentum 0 and a constant force 1. The equations
    of the interior control points of a step read `h ∫ ℓ_k = 0`, which no unknown can meet,
    and their Jacobian rows vanish."""
    term = dvi.IODETerm(
        lambda t, q, v, a: 0 * v, lambda t, q, v, a: jnp.ones_like(q),
        velocity=lambda t, q, p, a: p,
    )  # fmt: skip
    return term, (jnp.array([0.5]), jnp.array([0.0]))


def free_particle_into_sqrt():
    # L = ½v² − 0·√q: the force 0·(1/2√q) is NaN once the particle (speed 1 to the left,
    # from q = 0.25) reaches q < 0 on the third step.
    term = dvi.LagrangianTerm(lambda t, q, v, a: 0.5 * v @ v - 0.0 * jnp.sum(jnp.sqrt(q)))
    return term, (jnp.array([0.25]), jnp.array([-1.0]))


def assert_failed_at(sol, member, t_fail, kind):
    assert sol.result == member
    assert dvi.failure_kind(sol.result) == kind
    report = sol.solver_state.report
    assert float(report.t) == pytest.approx(t_fail)
    assert float(report.h) == pytest.approx(0.1)
    assert report.result == member
    line = dvi.describe_failure(sol)
    assert line.startswith(kind) and f"[{t_fail:.6g}, {t_fail + 0.1:.6g}]" in line
    assert "residual" in line
    # The accepted steps are kept, the failed step is NaN, later times are unsaved (inf).
    q = np.asarray(sol.ys[0][:, 0])
    n_ok = int(round(t_fail / 0.1)) + 1
    assert np.all(np.isfinite(q[:n_ok]))
    assert np.isnan(q[n_ok])
    assert np.all(np.isinf(q[n_ok + 1 :]))


def test_each_member_is_distinct_and_documented():
    values = {int(m._value) for m in STEP_FAILURES.values()}
    assert len(values) == len(STEP_FAILURES) == 8
    for name, member in STEP_FAILURES.items():
        assert getattr(diffrax.RESULTS, name) == member
        message = diffrax.RESULTS[member]
        assert message.startswith("diffrax_vi:") and "solver_state.report" in message


def test_max_iterations():
    problem = problems.harmonic_oscillator()
    sol = run(cheap(root_find_max_steps=1), problem.term, problem.y0)
    assert_failed_at(sol, diffrax.RESULTS.vi_step_max_iterations, 0.0, "maxiter")
    report = sol.solver_state.report
    assert int(report.iterations) == 1
    assert float(report.residual) > float(report.tolerance)


def test_stall():
    term, y0 = rootless()
    sol = run(cheap(), term, y0)
    assert_failed_at(sol, diffrax.RESULTS.vi_step_stalled, 0.0, "stalled")
    assert float(sol.solver_state.report.residual) > 1e-3


def test_nonfinite_keeps_the_accepted_steps():
    term, y0 = free_particle_into_sqrt()
    sol = run(cheap(), term, y0)
    assert_failed_at(sol, diffrax.RESULTS.vi_step_nonfinite, 0.2, "nonfinite")
    # The two accepted steps are the exact free flight.
    np.testing.assert_allclose(np.asarray(sol.ys[0][:3, 0]), [0.25, 0.15, 0.05], atol=1e-12)


def test_nonfinite_raises_with_its_message():
    term, y0 = free_particle_into_sqrt()
    with pytest.raises(Exception, match="diffrax_vi: a step produced NaN or inf"):
        jax.block_until_ready(run(cheap(), term, y0, throw=True).ys)


def test_singular():
    # Newton without regularisation on the vanishing Jacobian rows: the LU solve breaks down.
    term, y0 = rootless()
    sol = run(cheap(root_finder=dvi.RegularisedNewton(lam=0.0)), term, y0)
    assert_failed_at(sol, diffrax.RESULTS.vi_step_singular, 0.0, "singular")
    assert np.isfinite(float(sol.solver_state.report.residual))


def test_failure_kind_of_other_results():
    assert dvi.failure_kind(diffrax.RESULTS.successful) == "ok"
    assert dvi.failure_kind(diffrax.RESULTS.event_occurred) == "ok"
    assert dvi.failure_kind(diffrax.RESULTS.max_steps_reached) == "max_steps"
    assert dvi.failure_kind(optx.RESULTS.nonlinear_max_steps_reached) == "maxiter"
    assert dvi.failure_kind(optx.RESULTS.singular) == "singular"
    batched = diffrax.RESULTS.where(
        jnp.array(True), diffrax.RESULTS.vi_step_stalled, diffrax.RESULTS.successful
    )
    assert dvi.failure_kind(batched) == "stalled"
    with pytest.raises(TypeError, match="RESULTS member"):
        dvi.failure_kind("successful")


def test_successful_solve_reports_its_last_step():
    problem = problems.harmonic_oscillator()
    sol = run(cheap(), problem.term, problem.y0)
    assert sol.result == diffrax.RESULTS.successful
    assert dvi.describe_failure(sol) is None
    report = sol.solver_state.report
    assert float(report.t) == pytest.approx(0.2)
    assert float(report.residual) <= 1e-8
    assert np.all(np.isfinite(np.asarray(sol.ys[0])))


def test_result_names_of_one_result_and_of_a_batch():
    from diffrax_vi._results import result_names

    assert str(result_names(diffrax.RESULTS.successful)) == "successful"
    stalled = STEP_FAILURES["vi_step_stalled"]
    batch = jax.vmap(lambda ok: diffrax.RESULTS.where(ok, diffrax.RESULTS.successful, stalled))(
        jnp.array([True, False]))
    assert result_names(batch).tolist() == ["successful", "vi_step_stalled"]
    assert dvi.failure_kind(batch).tolist() == ["ok", "stalled"]
    with pytest.raises(TypeError, match="RESULTS member"):
        result_names("successful")
