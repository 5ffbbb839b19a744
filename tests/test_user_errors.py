"""What a new user trips over (issue 29): malformed states and times are refused with one
message that says what is expected and what was given; failure reports say what happened;
the state can be built from positions and velocities."""

from functools import partial

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._results import FAILURE_KINDS, STEP_FAILURES
from diffrax_vi._validation import check_state, check_times
from tests.helpers import motionless_cgvi

HO = problems.harmonic_oscillator()
TERM = HO.term
IODE = dvi.IODETerm(
    lambda t, q, v, a: v, lambda t, q, v, a: -0.5 * q, velocity=lambda t, q, p, a: p
)
Q, P = jnp.array([0.5]), jnp.array([0.0])
F32_TIMES = (jnp.float32(0.0), jnp.float32(0.2), jnp.float32(0.1))


cgvi = partial(motionless_cgvi, 2, 3)


def assert_names_the_form(error: pytest.ExceptionInfo, given: str) -> None:
    message = str(error.value)
    assert message.startswith("y0 = (q, p) must be a pair")
    assert "two 1-D real floating arrays of the same shape and dtype" in message
    assert f"got {given}" in message


# Each malformed y0 of the issue, with the description of it the message must give.
MALFORMED = {
    "shapes differ": ((Q, jnp.zeros(3)), "a tuple (float64[1], float64[3])"),
    "0-d arrays": ((jnp.array(0.5), jnp.array(0.0)), "a tuple (float64[], float64[])"),
    "shape (1, 1)": ((Q[None], P[None]), "a tuple (float64[1, 1], float64[1, 1])"),
    "complex": ((Q + 0j, P + 0j), "a tuple (complex128[1], complex128[1])"),
    "list": ([Q, P], "a list (float64[1], float64[1])"),
    "single array": (jnp.array([0.5, 0.0]), "a single array float64[2]"),
    "three arrays": ((Q, P, P), "a tuple (float64[1], float64[1], float64[1])"),
    # diffrax turns Python numbers into 0-d arrays before the check sees them.
    "Python floats": ((0.5, 0.0), "a tuple (float64[], float64[])"),
}


@pytest.mark.parametrize("case", MALFORMED, ids=list(MALFORMED))
@pytest.mark.filterwarnings("ignore:Complex dtype support")
def test_malformed_y0_through_diffeqsolve(case):
    # diffrax evaluates the term's vector field on y0 before the solver sees it: the term's
    # own check must answer first, for NetworkVI and for diffrax's solvers alike.
    y0, given = MALFORMED[case]
    for solver in (cgvi(), diffrax.Tsit5()):
        with pytest.raises(ValueError) as error:
            diffrax.diffeqsolve(TERM, solver, 0.0, 0.2, 0.1, y0)
        assert_names_the_form(error, given)


@pytest.mark.parametrize(
    "y0, given",
    [
        ((Q.astype(jnp.float32), P), "a tuple (float32[1], float64[1]) (its two arrays differ"),
        ((jnp.array([1]), jnp.array([0])), "a tuple (int64[1], int64[1]) (int64 is not floating)"),
        ((jnp.array([True]), jnp.array([False])), "a tuple (bool[1], bool[1]) (bool is not"),
        ((jnp.ones(1, complex), P), "a tuple (complex128[1], float64[1]) (complex128 is complex)"),
    ],
)
def test_wrong_dtypes_at_every_entry_point(y0, given):
    # Through diffeqsolve diffrax first promotes y0 to the dtype of the times (integers to
    # float, float32 next to float64 to float64), so these are refused where a state is
    # handed over directly: the vector field, NetworkVI.init and the shared check.
    entries = [
        lambda: check_state(y0),
        lambda: TERM.vf(0.0, y0, None),
        lambda: IODE.vf(0.0, y0, None),
        lambda: cgvi().init(TERM, 0.0, 0.1, y0, None),
    ]
    for entry in entries:
        with pytest.raises(ValueError) as error:
            entry()
        assert_names_the_form(error, given)


def test_mixed_float_dtypes_with_float32_times_refused_in_diffeqsolve():
    with pytest.raises(ValueError) as error:
        diffrax.diffeqsolve(TERM, cgvi(), *F32_TIMES, (Q.astype(jnp.float32), P))
    assert_names_the_form(error, "a tuple (float32[1], float64[1])")


def test_sympy_term_checks_the_number_of_coordinates():
    sympy = pytest.importorskip("sympy")
    q, v = sympy.symbols("q v")
    term = dvi.sympy_lagrangian_term(v**2 / 2 - q**2 / 4, [q], [v])
    with pytest.raises(ValueError, match=r"1 coordinates \['q'\].*shape \(1,\); got 2"):
        term.vf(0.0, (jnp.zeros(2), jnp.zeros(2)), None)
    with pytest.raises(ValueError, match="y0 = \\(q, p\\) must be a pair"):
        term.vf(0.0, [Q, P], None)


def test_valid_states_still_work_under_jit_vmap_and_grad():
    vf = jax.jit(lambda y: TERM.vf(0.0, y, None))
    v, f = vf((Q, P))
    assert v.shape == f.shape == (1,)
    batch = (jnp.linspace(0.1, 0.5, 3)[:, None], jnp.zeros((3, 1)))
    v, f = jax.vmap(lambda y: TERM.vf(0.0, y, None))(batch)
    np.testing.assert_allclose(np.asarray(f[:, 0]), -0.5 * np.linspace(0.1, 0.5, 3))
    dfdq = jax.grad(lambda q: TERM.vf(0.0, (q, P), None)[1][0])(Q)
    np.testing.assert_allclose(np.asarray(dfdq), [-0.5])
    # float32 and float16 states are valid too: the dtype is the working precision.
    for dtype in (jnp.float32, jnp.float16):
        assert check_state((Q.astype(dtype), P.astype(dtype)))[0].dtype == dtype


def test_standard_and_variational_solvers_still_integrate_a_valid_state():
    ts = jnp.linspace(0.0, 1.0, 11)
    q_ref, _ = HO.reference(np.asarray(ts))
    saveat = diffrax.SaveAt(ts=ts)
    tsit5 = diffrax.diffeqsolve(TERM, diffrax.Tsit5(), 0.0, 1.0, 0.1, (Q, P), saveat=saveat)
    vi = diffrax.diffeqsolve(TERM, cgvi(), 0.0, 1.0, 0.1, (Q, P), saveat=saveat)
    for sol in (tsit5, vi):
        assert sol.result == diffrax.RESULTS.successful
        assert np.max(np.abs(np.asarray(sol.ys[0]) - q_ref)) < 1e-4


# -- times -----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["t0", "t1", "dt0"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_concrete_non_finite_times_refused(name, value):
    times = dict(t0=0.0, t1=1.0, dt0=0.1)
    for kind in (float, np.float32, jnp.asarray):
        times[name] = kind(value)
        with pytest.raises(ValueError, match=f"{name} must be a finite time; got {name} = "):
            check_times(**times)
    check_times(t0=0.0, t1=jnp.asarray(1.0), dt0=None)  # finite and None pass


def test_manual_stepping_refuses_a_nan_time_at_trace_time():
    with pytest.raises(ValueError, match="t1 must be a finite time"):
        cgvi().init(TERM, 0.0, float("nan"), (Q, P), None)
    with pytest.raises(ValueError, match="t0 must be a finite time"):
        cgvi().init(TERM, jnp.asarray(jnp.inf), 0.1, (Q, P), None)


def test_traced_times_are_left_to_run_time():
    # Under jit a time has no value at trace time: the check must not fail on it.
    jax.jit(lambda t: check_times(t0=t) or t)(jnp.asarray(0.0))


@pytest.mark.parametrize(
    "t0, t1, dt0",
    [
        (jnp.nan, 0.2, 0.1), (0.0, jnp.nan, 0.1), (0.0, 0.2, jnp.nan),
        (-jnp.inf, 0.2, 0.1), (jnp.inf, 0.2, -0.1),
    ],
)
def test_nonfinite_times_inside_diffeqsolve_are_refused_at_run_time(t0, t1, dt0):
    """diffeqsolve traces the times before any solver sees them, so `NetworkVI.init` checks them
    when the program runs: without it a NaN t0 or t1 makes diffrax take no step and report
    success. Refused with throw=False too, for arrays and for Python numbers."""
    message = "t0 and t1 must be finite times"
    for kind in (float, jnp.asarray):
        with pytest.raises(Exception, match=message):
            sol = diffrax.diffeqsolve(
                TERM, cgvi(), kind(t0), kind(t1), kind(dt0), (Q, P), throw=False
            )
            sol.ys[0].block_until_ready()


def test_a_nan_time_in_one_lane_of_a_vmap_is_refused():
    def final(t1):
        sol = diffrax.diffeqsolve(TERM, cgvi(), 0.0, t1, 0.1, (Q, P), throw=False)
        return sol.ys[0][-1]

    assert np.all(np.isfinite(np.asarray(jax.vmap(final)(jnp.array([0.2, 0.3])))))
    with pytest.raises(Exception, match="t0 and t1 must be finite times"):
        jax.vmap(final)(jnp.array([0.2, jnp.nan])).block_until_ready()


def test_what_other_odd_times_do_inside_diffeqsolve():
    """The failures page's table: a zero dt0 fails the first step with vi_step_size_invalid, an
    infinite t1 steps until max_steps, an infinite dt0 is clipped to one step over [t0, t1]."""
    sol = diffrax.diffeqsolve(TERM, cgvi(), 0.0, 0.2, jnp.asarray(0.0), (Q, P), throw=False)
    assert dvi.failure_kind(sol.result) == "step_size"
    sol = diffrax.diffeqsolve(TERM, cgvi(), 0.0, jnp.inf, 0.1, (Q, P), throw=False, max_steps=4)
    assert dvi.failure_kind(sol.result) == "max_steps"
    sol = diffrax.diffeqsolve(TERM, cgvi(), 0.0, 0.2, jnp.inf, (Q, P), throw=False)
    assert int(sol.stats["num_steps"]) == 1 and sol.result == diffrax.RESULTS.successful


# -- failure reports -------------------------------------------------------------------------
def test_each_member_has_its_own_kind():
    kinds = [dvi.failure_kind(member) for member in STEP_FAILURES.values()]
    assert kinds == [
        "maxiter", "stalled", "nonfinite", "singular", "step_size", "constraint_drift",
        "constraint_unmet", "energy_jump",
    ]
    assert dvi.failure_kind(diffrax.RESULTS.max_steps_reached) == "max_steps"
    assert dvi.failure_kind(diffrax.RESULTS.dt_min_reached) == "dt_min"
    assert dvi.failure_kind(diffrax.RESULTS.nonlinear_divergence) == "diverged"
    assert dvi.failure_kind(diffrax.RESULTS.internal_error) == "other"
    # Every member of diffrax.RESULTS is classified, and the table names real members.
    assert set(FAILURE_KINDS) <= set(diffrax.RESULTS._name_to_item)


ROTATION = dvi.LagrangianTerm(lambda t, q, v, args: q[0] * v[1] - 0.5 * q @ q)
ROTATION_Y0 = (jnp.array([0.5, 0.2]), jnp.array([0.0, 0.5]))


def _rotation(activation, width, formulation):
    """Issue 29's degenerate example: five steps of 0.1 of L = q0 v1 - |q|²/2 (a rotation)."""
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, width), formulation=formulation)
    sol = diffrax.diffeqsolve(
        ROTATION, solver, 0.0, 0.5, 0.1, ROTATION_Y0, throw=False,
        saveat=diffrax.SaveAt(steps=True, solver_state=True),
    )  # fmt: skip
    n = int(sol.stats["num_accepted_steps"])
    t = np.asarray(sol.ts)[:n]
    exact = np.stack([0.5 * np.cos(t) - 0.2 * np.sin(t), 0.2 * np.cos(t) + 0.5 * np.sin(t)], 1)
    return sol, np.max(np.abs(np.asarray(sol.ys[0])[:n] - exact))


def test_constraint_drift_of_a_degenerate_lagrangian_fails_the_step():
    # The all-parameter step, tanh 10: every step converges, but p - ϑ(q) grows geometrically;
    # the monitor stops it once it exceeds sqrt(eps) (relative), with its own result.
    sol, _ = _rotation(dvi.tanh, 10, dvi.FreeEndpoints())
    assert dvi.failure_kind(sol.result) == "constraint_drift"
    report = sol.solver_state.report
    assert float(report.constraint) > np.sqrt(np.finfo(np.float64).eps)
    assert int(report.iterations) < 256  # its solve ended by converging, not at the cap
    line = dvi.describe_failure(sol)
    assert line.startswith("constraint_drift: step [") and "off the primary constraint" in line
    # GELU 8 drifts less (a few 1e-9) and still succeeds
    sol, err = _rotation(dvi.gelu, 8, dvi.FreeEndpoints())
    assert sol.result == diffrax.RESULTS.successful and err <= 1e-8
    assert 0 < float(sol.solver_state.report.constraint) <= np.sqrt(np.finfo(np.float64).eps)
    # the default (projected) step keeps the constraint: tanh 10 succeeds at round-off
    sol, err = _rotation(dvi.tanh, 10, None)
    assert sol.result == diffrax.RESULTS.successful and err <= 1e-13
    assert float(sol.solver_state.report.constraint) <= 1e-15


def test_well_posed_steps_report_the_constraint_without_failing():
    # CGVI(7) on the degenerate pendulum at h = 1: the end states are off the constraint by
    # the step's truncation error (bounded over the run), which is reported, not failed.
    problem = problems.pendulum()
    sol = diffrax.diffeqsolve(
        problem.term, dvi.CGVI(7), 0.0, 10.0, 1.0, problem.y0, args=problem.args,
        saveat=diffrax.SaveAt(t1=True, solver_state=True),
    )  # fmt: skip
    assert sol.result == diffrax.RESULTS.successful
    assert float(sol.solver_state.report.constraint) > np.sqrt(np.finfo(np.float64).eps)
    q_ref, _ = problem.reference(np.array([10.0]))
    assert np.max(np.abs(np.asarray(sol.ys[0][-1]) - q_ref[-1])) <= 1e-5


def test_regular_lagrangians_report_no_constraint():
    sol = _solve((Q, P))
    assert sol.result == diffrax.RESULTS.successful
    assert float(sol.solver_state.report.constraint) == 0.0


def _solve(y0, *, t1=0.3, **kwargs):
    return diffrax.diffeqsolve(
        TERM, cgvi(), 0.0, t1, 0.1, y0, throw=False,
        saveat=diffrax.SaveAt(t1=True, solver_state=True), **kwargs,
    )  # fmt: skip


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf])
def test_non_finite_initial_state_gets_its_own_message(bad):
    sol = _solve((jnp.array([bad]), P))
    line = dvi.describe_failure(sol)
    assert line.startswith("nonfinite: the step [0, 0.1]")
    assert "the initial state y0 (q, p) is not finite" in line
    assert "tolerance nan" not in line and "Check the Lagrangian" not in line


def test_max_steps_says_the_budget_ran_out_and_where():
    sol = _solve((Q, P), t1=3.0, max_steps=5)
    assert dvi.failure_kind(sol.result) == "max_steps"
    line = dvi.describe_failure(sol)
    assert line.startswith("max_steps: the step budget ran out: all 5 steps of max_steps")
    assert "stopped at t = 0.5, short of t1 = 3" in line
    assert "[0.4, 0.5]" in line and "larger max_steps" in line


# -- state from velocities -------------------------------------------------------------------
def test_state_from_velocity_gives_the_canonical_momentum():
    # A charge in a magnetic field B = 1 along z: L = ½ m |v|² + (q × A)·v with A = ½ B × x,
    # so p = m v + A(x), which differs from the velocity.
    m = 2.0

    def lagrangian(t, x, v, args):
        a = 0.5 * jnp.array([-x[1], x[0]])
        return 0.5 * m * v @ v + a @ v

    term = dvi.LagrangianTerm(lagrangian)
    x0, v0 = jnp.array([1.0, 0.5]), jnp.array([0.0, 1.0])
    q0, p0 = term.state_from_velocity(0.0, x0, v0)
    assert q0 is x0 or np.array_equal(q0, x0)
    np.testing.assert_allclose(np.asarray(p0), m * np.asarray(v0) + [-0.25, 0.5])
    # The velocity map inverts it.
    np.testing.assert_allclose(np.asarray(term.velocity(0.0, q0, p0, None)), np.asarray(v0))
    # IODETerm: the momentum map itself.
    q0, p0 = IODE.state_from_velocity(0.0, Q, jnp.array([0.3]))
    np.testing.assert_allclose(np.asarray(p0), [0.3])
    # float32 in, float32 out.
    q0, p0 = term.state_from_velocity(0.0, x0.astype(jnp.float32), v0.astype(jnp.float32))
    assert p0.dtype == jnp.float32


def test_state_from_velocity_refuses_bad_input():
    expected = r"\(q0, v0\) must be a pair .* got a tuple \(float64\[1\], float64\[2\]\)"
    with pytest.raises(ValueError, match=expected):
        TERM.state_from_velocity(0.0, Q, jnp.zeros(2))
    with pytest.raises(ValueError, match="t0 must be a finite time"):
        TERM.state_from_velocity(float("nan"), Q, P)


# -- what the docs promise ---------------------------------------------------------------------
def test_the_precision_table_of_the_docs():
    """docs/how-to/precision.md: with x64 on, diffrax promotes a float32 y0 to the dtype of
    the times, and Python-number times alone are float64."""
    y0 = (Q.astype(jnp.float32), P.astype(jnp.float32))
    f32 = jnp.float32
    ts64, ts32 = jnp.linspace(0.0, 0.2, 3), jnp.linspace(0.0, 0.2, 3, dtype=f32)
    cases = [
        ((0.0, 0.2, 0.1), None, jnp.float64),
        ((f32(0.0), f32(0.2), 0.1), None, jnp.float32),
        ((f32(0.0), f32(0.2), f32(0.1)), ts64, jnp.float64),
        ((f32(0.0), f32(0.2), f32(0.1)), ts32, jnp.float32),
    ]
    for times, ts, dtype in cases:
        saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)
        sol = diffrax.diffeqsolve(TERM, cgvi(), *times, y0, saveat=saveat)
        assert sol.ys[0].dtype == sol.ys[1].dtype == dtype


def test_the_adjoint_table_of_the_gradients_page():
    def final(q0, adjoint):
        sol = diffrax.diffeqsolve(
            TERM, cgvi(), 0.0, 0.3, 0.1, (q0, P), adjoint=adjoint,
            saveat=diffrax.SaveAt(t1=True),
        )  # fmt: skip
        return sol.ys[0][-1, 0]

    exact = np.cos(np.sqrt(0.5) * 0.3)  # d q(t) / d q0 of the oscillator
    for adjoint in (diffrax.DirectAdjoint(), diffrax.ForwardMode()):
        _, tangent = jax.jvp(lambda q: final(q, adjoint), (Q,), (jnp.ones(1),))
        assert abs(float(tangent) - exact) < 1e-4  # a degree-2 cGVI at h = 0.1
    with pytest.raises(TypeError, match="forward-mode autodiff"):
        jax.jvp(lambda q: final(q, diffrax.RecursiveCheckpointAdjoint()), (Q,), (jnp.ones(1),))
    # diffrax's TermAndSolverIncompatible (a ValueError, not exported): the adjoint term is not
    # a mechanical term.
    with pytest.raises(ValueError, match="Terms are not compatible with solver"):
        jax.grad(lambda q: final(q, diffrax.BacksolveAdjoint()))(Q)
