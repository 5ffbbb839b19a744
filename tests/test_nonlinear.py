"""The damped root finders (`diffrax_vi._root_finder.damped_newton`): `LevenbergMarquardt` and
`RegularisedNewton`, their tolerances, Jacobian options and restarts."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from diffrax_vi._root_finder.damped_newton import (
    LevenbergMarquardt,
    RegularisedNewton,
    default_tolerances,
)
from diffrax_vi._root_finder.step_hints import StepHints, step_options

F64 = jnp.float64


# -- 3. root finders -------------------------------------------------------------------------

_A = np.eye(10) * 3.0 + 0.1 * np.arange(100.0).reshape(10, 10) / 100
_XSTAR = np.linspace(-1.0, 1.0, 10)
_B = _A @ _XSTAR + 0.5 * np.sin(_XSTAR) + _XSTAR**3


def well_posed(y, args):
    """A 10-dimensional system with the unique root `_XSTAR`, in the dtype of `y`."""
    return jnp.asarray(_A, y.dtype) @ y + 0.5 * jnp.sin(y) + y**3 - jnp.asarray(_B, y.dtype)


def degenerate(y, args):
    """Two copies of one equation in two unknowns: roots form the curve `a w³ = 2`; the
    Jacobian is singular everywhere."""
    a, w = y
    r = a * w**3 - 2.0
    return jnp.stack([r, r])


ROOT_FINDERS = [LevenbergMarquardt(), RegularisedNewton()]
ids = lambda s: type(s).__name__


def _find(fn, solver, y0, max_steps=100, options=None, **kwargs):
    """`optimistix.root_find`; `options` names the solver's step hints (`StepHints`)."""
    if options is not None:
        options = step_options(StepHints(**options))
    return optx.root_find(fn, solver, y0, None, throw=False, max_steps=max_steps,
                          options=options, **kwargs)


@pytest.mark.parametrize("solver", ROOT_FINDERS, ids=ids)
def test_root_finder_well_posed_float64(solver):
    sol = _find(well_posed, solver, jnp.zeros(10, F64))
    assert sol.result == optx.RESULTS.successful
    assert sol.value.dtype == F64
    assert float(jnp.max(jnp.abs(sol.value - _XSTAR))) <= 1e-13
    assert float(jnp.max(jnp.abs(well_posed(sol.value, None)))) <= 64 * np.finfo(np.float64).eps
    assert int(sol.stats["num_steps"]) <= 8


@pytest.mark.parametrize("solver", ROOT_FINDERS, ids=ids)
def test_root_finder_converges_quadratically(solver):
    # With a fresh Jacobian on every iteration (a reused one converges linearly).
    solver = type(solver)(reuse_jacobian=0)
    fn = lambda y, args: (well_posed(y, args), None)  # the (out, aux) form optimistix passes
    y, opts, tags = jnp.zeros(10, F64), {}, frozenset()
    state = solver.init(fn, y, None, opts, None, None, tags)
    step = jax.jit(lambda y, state: solver.step(fn, y, None, opts, state, tags)[:2])
    errors = []
    for _ in range(6):
        y, state = step(y, state)
        errors.append(float(jnp.max(jnp.abs(y - _XSTAR))))
    # Once in the basin, e_{k+1} <= C e_k^2 (measured C < 0.5) until rounding takes over.
    fast = [(e0, e1) for e0, e1 in zip(errors, errors[1:], strict=False) if 1e-12 < e0 < 0.05]
    assert len(fast) >= 2, errors
    for e0, e1 in fast:
        assert e1 <= 5.0 * e0**2, errors
    assert errors[-1] <= 1e-14


@pytest.mark.parametrize("solver", ROOT_FINDERS, ids=ids)
def test_root_finder_jacobian_reuse(solver):
    """A reused Jacobian saves evaluations, not accuracy; at most `reuse_jacobian` in a row."""
    fn = lambda y, args: (well_posed(y, args), None)
    y, opts, tags = jnp.zeros(10, F64), {}, frozenset()
    counts = {}
    for reuse in (0, 1, 3):
        s = type(solver)(reuse_jacobian=reuse)
        state = s.init(fn, y, None, opts, None, None, tags)
        step = jax.jit(lambda y, st, s=s: s.step(fn, y, None, opts, st, tags)[:2])
        term = jax.jit(lambda y, st, s=s: s.terminate(fn, y, None, opts, st, tags))
        yk, fresh, run = y, 0, 0
        for _ in range(40):
            yk, state = step(yk, state)
            fresh += int(state.exact)
            run = 0 if bool(state.exact) else run + 1
            assert run <= reuse
            if bool(term(yk, state)[0]):
                break
        assert float(jnp.max(jnp.abs(yk - _XSTAR))) <= 1e-13
        counts[reuse] = fresh
    assert counts[3] < counts[0] and counts[1] <= counts[0], counts
    with pytest.raises(ValueError, match="reuse_jacobian"):
        LevenbergMarquardt(reuse_jacobian=-1)
    with pytest.raises(ValueError, match="settle"):
        RegularisedNewton(settle=1.5)


def test_levenberg_marquardt_non_isolated_roots():
    y0 = jnp.array([1.0, 0.5], F64)
    sol = _find(degenerate, LevenbergMarquardt(), y0)
    assert sol.result == optx.RESULTS.successful
    assert bool(jnp.all(jnp.isfinite(sol.value)))
    assert float(jnp.max(jnp.abs(degenerate(sol.value, None)))) <= 1e-13
    assert int(sol.stats["num_steps"]) <= 10
    # The plain LU Newton step is undefined on this system.
    newton = _find(degenerate, optx.Newton(rtol=1e-10, atol=1e-10), y0)
    assert newton.result != optx.RESULTS.successful


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32, jnp.float16])
def test_levenberg_marquardt_damps_harder_after_failed_line_searches(dtype):
    """After `k` failed line searches the damping is `stall_damping^k·λ‖F‖`: the step
    shortens and turns towards steepest descent `−JᵀF`; `stall_damping=1` keeps it; the
    growth cannot overflow float16."""
    rng = np.random.default_rng(3)
    jac = rng.standard_normal((6, 6))
    jac[:, 0] = jac[:, 1] * (1 + 1e-3)  # nearly singular
    f = rng.standard_normal(6)
    jac_t, f_t = jnp.asarray(jac, dtype), jnp.asarray(f, dtype)
    descent = -(jac.T @ f)

    def step(solver, k):
        d = solver.direction(jac_t, f_t, jnp.asarray(k, jnp.int32))
        assert d.dtype == dtype and bool(jnp.all(jnp.isfinite(d)))
        d = np.asarray(d, np.float64)
        return np.linalg.norm(d), d @ descent / np.linalg.norm(d) / np.linalg.norm(descent)

    grows, fixed = LevenbergMarquardt(), LevenbergMarquardt(stall_damping=1)
    lengths, cosines = zip(*(step(grows, k) for k in range(4)), strict=True)
    assert all(b < 0.9 * a for a, b in zip(lengths, lengths[1:], strict=False)), lengths
    assert lengths[-1] < 0.01 * lengths[0], lengths
    assert cosines[0] < 0.9 and cosines[-1] > 0.99, cosines
    same = [step(fixed, k)[0] for k in range(4)]
    np.testing.assert_allclose(same, same[0], rtol=1e-6)
    np.testing.assert_allclose(same[0], lengths[0], rtol=1e-6)
    far = grows.direction(jac_t, f_t, jnp.asarray(30, jnp.int32))  # 100^30: capped, not inf
    assert bool(jnp.all(jnp.isfinite(far)))
    for bad in (0.5, True, "10", float("nan")):
        with pytest.raises(ValueError, match="stall_damping"):
            LevenbergMarquardt(stall_damping=bad)


@pytest.mark.parametrize("solver", ROOT_FINDERS, ids=ids)
def test_root_finder_no_root_is_not_successful(solver):
    no_root = lambda y, args: y**2 + 1.0
    sol = _find(no_root, solver, jnp.array([0.3, -0.7], F64), max_steps=200)
    assert sol.result != optx.RESULTS.successful
    assert int(sol.stats["num_steps"]) < 200  # gives up by itself (patience), not max_steps
    # With a small step budget: max_steps_reached, never a silent success.
    sol = _find(no_root, solver, jnp.array([0.3, -0.7], F64), max_steps=5)
    assert sol.result != optx.RESULTS.successful


@pytest.mark.parametrize("cls", [LevenbergMarquardt, RegularisedNewton], ids=lambda c: c.__name__)
def test_root_finder_reference_convergence_test(cls):
    # y² + c has no root; its smallest residual c = 1e-10 is 1e-10 of the seed's (~1): the
    # reference's test (max|F| <= 8 eps + sqrt(eps) max|F(x0)| once x stops moving) takes
    # it, ours does not.
    # (RegularisedNewton's shift keeps stepping by about c/λ near the minimum, so x never
    # stops moving there: it ends by the stall rule instead.)
    floor = lambda y, args: y**2 + 1e-10
    y0 = jnp.array([1.0, -0.5], F64)
    strict = _find(floor, cls(), y0, max_steps=300)
    assert strict.result != optx.RESULTS.successful
    lax = _find(floor, cls(convergence="reference"), y0, max_steps=300)
    assert lax.result == optx.RESULTS.successful
    if cls is LevenbergMarquardt:  # by the test itself, before any stall
        assert float(jnp.max(floor(lax.value, None))) <= 1e-10 + 1.5e-8
        assert int(lax.stats["num_steps"]) < int(strict.stats["num_steps"])
    # As in the reference, a stalled solve is returned as converged, however large its
    # residual; the iteration cap and a NaN residual still fail.
    no_root = lambda y, args: y**2 + 1.0
    sol = _find(no_root, cls(convergence="reference"), jnp.array([0.3, -0.7], F64),
                max_steps=200)
    assert sol.result == optx.RESULTS.successful
    assert int(sol.stats["num_steps"]) < 200
    capped = _find(no_root, cls(convergence="reference"), jnp.array([0.3, -0.7], F64),
                   max_steps=5)
    assert capped.result == optx.RESULTS.nonlinear_max_steps_reached
    nan = _find(lambda y, args: jnp.log(y - 1.0), cls(convergence="reference"),
                jnp.array([0.5], F64))
    assert nan.result != optx.RESULTS.successful
    # A root is found as accurately as with our test.
    exact = _find(well_posed, cls(convergence="reference"), jnp.zeros(10, F64))
    assert exact.result == optx.RESULTS.successful
    assert float(jnp.max(jnp.abs(exact.value - _XSTAR))) <= 1e-13
    with pytest.raises(ValueError, match="convergence"):
        cls(convergence="loose")


@pytest.mark.parametrize("solver", ROOT_FINDERS, ids=ids)
def test_root_finder_nan_residual_is_not_successful(solver):
    nan_everywhere = lambda y, args: jnp.sqrt(y) - 3.0 + jnp.log(y - 100.0)
    sol = _find(nan_everywhere, solver, jnp.array([1.0, 2.0], F64))
    assert sol.result != optx.RESULTS.successful
    assert int(sol.stats["num_steps"]) <= 2  # detected at once, not after running out of patience

    # Finite at the start, NaN beyond a wall the full Newton step crosses.
    def wall(y, args):
        return jnp.where(y < 2.0, y - 5.0, jnp.nan)

    sol = _find(wall, solver, jnp.array([0.0], F64))
    assert sol.result != optx.RESULTS.successful


@pytest.mark.parametrize("solver", ROOT_FINDERS, ids=ids)
def test_root_finder_float32(solver):
    sol = _find(well_posed, solver, jnp.zeros(10, jnp.float32))
    assert sol.result == optx.RESULTS.successful
    assert sol.value.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(sol.value - _XSTAR))) <= 1e-5


def floor_system(y, args):
    """Inconsistent by 1e-9: the least-squares residual stops at 5e-10, far above `ftol` but
    below `floor`; `y[1]` does not enter."""
    return jnp.stack([y[0] - 1.0, y[0] - 1.0 + 1e-9])


@pytest.mark.parametrize("solver", ROOT_FINDERS, ids=ids)
def test_root_finder_options_honoured(solver):
    y0 = jnp.zeros(2, F64)
    # Without outputs of interest a residual floor at 5e-10 > eps^(3/4) is a failure ...
    plain = _find(floor_system, solver, y0, max_steps=200)
    assert plain.result != optx.RESULTS.successful
    # ... with outputs that settled, it is converged.
    calls = []

    def outputs(y):
        calls.append(None)
        return {"x": y[0]}

    sol = _find(floor_system, solver, y0, max_steps=200, options=dict(outputs=outputs))
    assert calls, "the outputs callable was never called"
    assert sol.result == optx.RESULTS.successful
    assert float(sol.value[0]) == pytest.approx(1.0 - 5e-10, abs=1e-9)
    assert int(sol.stats["num_steps"]) < int(plain.stats["num_steps"])
    # A large scale loosens the tolerance to ftol·scale.
    scaled = _find(floor_system, solver, y0, max_steps=200, options=dict(scale=1e6))
    assert scaled.result == optx.RESULTS.successful

    # The scale also stops a well-posed solve earlier.
    exact = _find(well_posed, solver, jnp.zeros(10, F64))
    loose = _find(well_posed, solver, jnp.zeros(10, F64), options=dict(scale=1e8))
    assert loose.result == optx.RESULTS.successful
    assert int(loose.stats["num_steps"]) < int(exact.stats["num_steps"])
    ftol = default_tolerances(F64)["ftol"]
    assert float(jnp.max(jnp.abs(well_posed(loose.value, None)))) <= ftol * 1e8


def test_root_finder_explicit_ftol():
    loose = _find(well_posed, LevenbergMarquardt(ftol=1e-3), jnp.zeros(10, F64))
    assert loose.result == optx.RESULTS.successful
    residual = float(jnp.max(jnp.abs(well_posed(loose.value, None))))
    assert 1e-12 < residual <= 1e-3


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_default_tolerances_scale_with_eps(dtype):
    eps = float(jnp.finfo(dtype).eps)
    tol = default_tolerances(dtype)
    assert tol["ftol"] == pytest.approx(min(64 * eps, eps**0.75))
    assert tol["ftol"] <= tol["floor"]
    assert tol["otol"] == pytest.approx(64 * eps)
    assert tol["otol_slow"] == pytest.approx(eps**0.75)
    assert tol["floor"] == pytest.approx(eps**0.5)
    assert tol["floor_moving"] == pytest.approx(eps**0.625)
    assert tol["floor_no_outputs"] == pytest.approx(eps**0.75)
    assert tol["floor_no_outputs"] < tol["floor_moving"] < tol["floor"] < 1


def test_default_tolerances_float64_values():
    tol = default_tolerances(jnp.float64)
    assert tol["ftol"] == pytest.approx(64 * 2.0**-52)
    assert tol["floor"] == pytest.approx(2.0**-26)
    assert tol["ftol"] < tol["floor_no_outputs"] < tol["floor_moving"] < tol["floor"]
    assert default_tolerances(jnp.float32)["ftol"] <= default_tolerances(jnp.float32)["floor"]
    # Every tolerance grows with eps: float32 ones are looser than float64 ones.
    tol32 = default_tolerances(jnp.float32)
    assert tol32["ftol"] == pytest.approx(2.0 ** (-23 * 0.75))  # eps^(3/4) < 64·eps in float32
    assert all(tol32[name] > tol[name] for name in tol)

def test_structured_jacobian_needs_the_callers_matrix():
    with pytest.raises(ValueError, match="the jacobian of its StepHints"):
        _find(well_posed, LevenbergMarquardt(jacobian="structured"), jnp.zeros(10, F64))
    given = lambda y, args: jax.jacfwd(lambda v: well_posed(v, args))(y)
    sol = _find(well_posed, LevenbergMarquardt(jacobian="structured"), jnp.zeros(10, F64),
                options=dict(jacobian=given))
    assert sol.result == optx.RESULTS.successful
    assert float(jnp.max(jnp.abs(sol.value - _XSTAR))) <= 1e-13
    with pytest.raises(ValueError, match="jacobian must be"):
        LevenbergMarquardt(jacobian="blocks")

def _no_root_near_zero(y, args):
    """`(y² + 1)(y − 3)`: one root, at 3; the residual's size has a local minimum (2.9 at
    y ≈ 0.18, where the derivative vanishes), where `LevenbergMarquardt` from −1 stalls."""
    return (y**2 + 1) * (y - 3)


def test_root_finder_restarts_once_from_the_fallback():
    solver, start = LevenbergMarquardt(), jnp.array(-1.0, F64)
    stalled = _find(_no_root_near_zero, solver, start)
    assert stalled.result != optx.RESULTS.successful
    assert not bool(stalled.state.restarted)
    fallback = dict(fallback=lambda args: jnp.array(4.0, F64))
    sol = _find(_no_root_near_zero, solver, start, options=fallback)
    assert sol.result == optx.RESULTS.successful and bool(sol.state.restarted)
    assert abs(float(sol.value) - 3.0) <= 1e-12
    # the caller may rule the restart out at run time ...
    off = _find(_no_root_near_zero, solver, start,
                options=dict(fallback_usable=lambda args: jnp.array(False), **fallback))
    assert off.result != optx.RESULTS.successful and not bool(off.state.restarted)
    # ... and it happens once: a fallback that stalls too ends the solve as a failure
    again = _find(_no_root_near_zero, solver, start, options=dict(fallback=lambda args: start))
    assert again.result != optx.RESULTS.successful and bool(again.state.restarted)
    # under vmap only the member that needs it restarts; the other keeps its own path
    batch = jax.vmap(lambda y: _find(_no_root_near_zero, solver, y, options=fallback))(
        jnp.array([-1.0, 2.5], F64))
    assert bool(jnp.all(batch.result == optx.RESULTS.successful))
    np.testing.assert_allclose(batch.value, 3.0, atol=1e-12)
    assert batch.state.restarted.tolist() == [True, False]


def test_root_finder_starts_at_the_fallback_when_told():
    """The hint `start_at_fallback`: the solve begins at the fallback (the given point only
    gives the shape), on the same iterations as a solve begun there, counts no restart, and
    never restarts after it."""
    solver = LevenbergMarquardt()
    direct = _find(_no_root_near_zero, solver, jnp.array(4.0, F64))
    options = dict(fallback=lambda args: jnp.array(4.0, F64),
                   start_at_fallback=lambda args: jnp.array(True))
    # from the given point −1 the solve would stall; and 3, a root, would end it at once
    for given in (-1.0, 3.0):
        sol = _find(_no_root_near_zero, solver, jnp.array(given, F64), options=options)
        assert sol.result == optx.RESULTS.successful and not bool(sol.state.restarted)
        assert float(sol.value) == float(direct.value)
        assert int(sol.stats["num_steps"]) == int(direct.stats["num_steps"])  # same path
    # a fallback that stalls ends the solve as a failure: no second start from it
    stalls = dict(fallback=lambda args: jnp.array(-1.0, F64),
                  start_at_fallback=lambda args: jnp.array(True))
    sol = _find(_no_root_near_zero, solver, jnp.array(4.0, F64), options=stalls)
    assert sol.result != optx.RESULTS.successful and not bool(sol.state.restarted)
    # decided at run time, per member of a batch: one starts at the fallback (4, where the
    # given −1 would stall), the other keeps its own start and restarts there when it fails
    options = dict(fallback=lambda args: jnp.array(4.0, F64), start_at_fallback=lambda a: a)
    batch = jax.vmap(lambda y, start: optx.root_find(
        _no_root_near_zero, solver, y, start, throw=False, max_steps=100,
        options=step_options(StepHints(**options))))(
        jnp.array([-1.0, -1.0], F64), jnp.array([True, False]))
    assert bool(jnp.all(batch.result == optx.RESULTS.successful))
    np.testing.assert_allclose(batch.value, 3.0, atol=1e-12)
    assert batch.state.restarted.tolist() == [False, True]


def test_regularised_newton_restarts_too():
    """`y² + 1` has no root: the solve stalls, restarts from the fallback, stalls again and
    fails."""
    sol = _find(lambda y, args: y**2 + 1, RegularisedNewton(), jnp.array(0.5, F64),
                options=dict(fallback=lambda args: jnp.array(-0.5, F64)))
    assert sol.result != optx.RESULTS.successful and bool(sol.state.restarted)

def test_jacobian_modes_agree():
    def fn(x, _):
        return jnp.array([x[0] ** 2 + x[1] - 2.0, jnp.sin(x[0]) * x[1] - jnp.sin(1.0)])

    x0 = jnp.array([1.3, 0.6])
    roots = []
    for mode in ("fwd", "rev"):
        sol = optx.root_find(fn, dvi.LevenbergMarquardt(jacobian=mode), x0, max_steps=50)
        roots.append(np.asarray(sol.value))
        assert int(sol.stats["num_steps"]) <= 10
    np.testing.assert_allclose(roots[0], [1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(roots[0], roots[1], atol=1e-14)


def test_jacobian_mode_is_checked():
    with pytest.raises(ValueError, match="jacobian must be"):
        dvi.LevenbergMarquardt(jacobian="central")
