"""Unit tests of the building blocks: quadrature, activations, root finders, Lagrange weights,
the shallow-network ansatz, the free-endpoint equations and the midpoint seed trajectory."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi.activations import ReLUk, activation_name, check_activation
from diffrax_vi.formulation import (
    FreeEndpoints,
    InterpolatingEndpoints,
    StepContext,
    action_gradient,
    stage_values,
)
from diffrax_vi.interpolation import lagrange_weights
from diffrax_vi.nonlinear import LevenbergMarquardt, RegularisedNewton, default_tolerances
from diffrax_vi.quadrature import GaussLegendre, Simpson
from diffrax_vi.seeding.fit import LeastSquaresFit
from diffrax_vi.seeding.trajectories import implicit_midpoint
from diffrax_vi.terms import IODETerm, LagrangianTerm

F64 = jnp.float64


def _integrate(rule, f):
    c, b = rule.nodes_weights(F64)
    return float(jnp.sum(b * f(c)))


# -- 1. quadrature ---------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6])
def test_gauss_legendre_exact_up_to_degree_2n_minus_1(n):
    rule = GaussLegendre(n)
    for k in range(2 * n):
        assert _integrate(rule, lambda x: x**k) == pytest.approx(1 / (k + 1), abs=1e-14), k
    # Degree 2n is not integrated exactly: the error is (n!)^4 / ((2n+1) ((2n)!)^2) > 0.
    err = 1 / (2 * n + 1) - _integrate(rule, lambda x: x ** (2 * n))
    expected = math.factorial(n) ** 4 / ((2 * n + 1) * math.factorial(2 * n) ** 2)
    assert err == pytest.approx(expected, rel=1e-6)
    assert rule.order == 2 * n
    assert rule.num_nodes == n


@pytest.mark.parametrize("n", [1, 3, 8])
def test_gauss_legendre_nodes_in_unit_interval_weights_sum_to_one(n):
    c, b = GaussLegendre(n).nodes_weights(F64)
    assert c.shape == b.shape == (n,)
    assert float(jnp.sum(b)) == pytest.approx(1.0, abs=1e-15)
    assert bool(jnp.all((c > 0) & (c < 1))) and bool(jnp.all(b > 0))
    assert bool(jnp.all(jnp.diff(c) > 0))


@pytest.mark.parametrize("rule", [GaussLegendre(4), Simpson(6)])
@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_quadrature_dtype_honoured(rule, dtype):
    c, b = rule.nodes_weights(dtype)
    assert c.dtype == jnp.dtype(dtype) and b.dtype == jnp.dtype(dtype)
    tol = {jnp.float16: 2e-3, jnp.float32: 1e-6, jnp.float64: 1e-15}[dtype]
    assert float(jnp.sum(b.astype(F64))) == pytest.approx(1.0, abs=tol)


@pytest.mark.parametrize("n", [2, 4, 10])
def test_simpson_exact_for_cubics_not_quartics(n):
    rule = Simpson(n)
    c, b = rule.nodes_weights(F64)
    np.testing.assert_allclose(np.asarray(c), np.arange(n + 1) / n, atol=0)
    assert float(jnp.sum(b)) == pytest.approx(1.0, abs=1e-15)
    cubic = lambda x: 2.0 - 3.0 * x + 5.0 * x**2 - 7.0 * x**3
    assert _integrate(rule, cubic) == pytest.approx(2.0 - 1.5 + 5 / 3 - 7 / 4, abs=1e-14)
    # Composite Simpson error for x^4: (1/180) h^4 * 4! with h = 1/n.
    err = _integrate(rule, lambda x: x**4) - 0.2
    assert err == pytest.approx(24 / 180 / n**4, rel=1e-8)


@pytest.mark.parametrize("n", [0, 1, 3, 7, -2, 2.0, True])
def test_simpson_refuses_odd_or_nonpositive(n):
    with pytest.raises(ValueError, match="even, positive"):
        Simpson(n)


@pytest.mark.parametrize("n", [0, -1, 2.0, True])
def test_gauss_legendre_refuses_bad_counts(n):
    with pytest.raises(ValueError, match="positive integer"):
        GaussLegendre(n)


# -- 2. activations --------------------------------------------------------------------------

ACTIVATIONS = [dvi.tanh, dvi.sigmoid, dvi.sin, dvi.gelu, dvi.elu, dvi.relu_k(1), dvi.relu_k(3)]


@pytest.mark.parametrize("activation", ACTIVATIONS, ids=activation_name)
@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_activation_keeps_dtype(activation, dtype):
    x = jnp.linspace(-2, 2, 9, dtype=dtype)
    y = activation(x)
    assert y.dtype == jnp.dtype(dtype)
    assert y.shape == x.shape
    assert bool(jnp.all(jnp.isfinite(y)))
    check_activation(activation, dtype)  # does not raise
    # Also under jit (static activation, traced input).
    assert jax.jit(activation)(x).dtype == jnp.dtype(dtype)


def test_activation_values():
    x = jnp.linspace(-2, 2, 9, dtype=F64)
    np.testing.assert_allclose(dvi.relu_k(3)(x), np.maximum(np.asarray(x), 0) ** 3)
    np.testing.assert_allclose(dvi.sigmoid(x), 1 / (1 + np.exp(-np.asarray(x))), rtol=1e-14)
    np.testing.assert_allclose(dvi.elu(x), np.where(x > 0, x, np.expm1(np.asarray(x))))


@pytest.mark.parametrize("k", [0, -1, 2.5, True, "3"])
def test_relu_k_refuses_bad_power(k):
    with pytest.raises(ValueError, match="relu_k"):
        dvi.relu_k(k)


def test_relu_k_hashable_and_equal_by_k():
    a, b, c = dvi.relu_k(3), dvi.relu_k(3), dvi.relu_k(4)
    assert isinstance(a, ReLUk)
    assert a == b and hash(a) == hash(b)
    assert a != c
    assert len({a, b, c}) == 2
    assert repr(a) == "relu_k(3)"
    # Usable as a static field: equal bases compare equal and hash equally.
    assert dvi.ShallowNetBasis(a, 4) == dvi.ShallowNetBasis(b, 4)
    assert hash(dvi.ShallowNetBasis(a, 4)) == hash(dvi.ShallowNetBasis(b, 4))


def promoting_activation(x):
    return x * jnp.asarray(2.0, dtype=jnp.float64)


def stacking_activation(x):
    return jnp.stack([x, x])


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32])
def test_check_activation_refuses_promotion(dtype):
    with pytest.raises(ValueError, match="promoting_activation.*promotes"):
        check_activation(promoting_activation, dtype)
    with pytest.raises(ValueError, match="promoting_activation"):
        dvi.ShallowNetBasis(promoting_activation, 3).check(dtype)


def test_check_activation_refuses_non_elementwise():
    with pytest.raises(ValueError, match="stacking_activation.*elementwise"):
        check_activation(stacking_activation, jnp.float64)


def test_check_activation_refuses_failing_and_nonfinite():
    def broken(x):
        raise RuntimeError("boom")

    def log_negative(x):
        return jnp.log(x - 1)

    with pytest.raises(ValueError, match="broken.*boom"):
        check_activation(broken, jnp.float32)
    with pytest.raises(ValueError, match="log_negative.*not finite"):
        check_activation(log_negative, jnp.float64)


def test_check_activation_works_while_tracing():
    @jax.jit
    def f(x):
        check_activation(promoting_activation, x.dtype)
        return x

    with pytest.raises(ValueError, match="promotes"):
        f(jnp.ones(2, jnp.float32))


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


def _find(fn, solver, y0, max_steps=100, **kwargs):
    return optx.root_find(fn, solver, y0, None, throw=False, max_steps=max_steps, **kwargs)


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


# -- 4. Lagrange weights ---------------------------------------------------------------------

POINTS = (0.0, 0.5 - math.sqrt(15) / 10, 0.5, 0.5 + math.sqrt(15) / 10, 1.0)


def test_lagrange_weights_kronecker_at_points():
    for i, x in enumerate(POINTS):
        w = lagrange_weights(POINTS, jnp.asarray(x, F64))
        expected = np.zeros(len(POINTS))
        expected[i] = 1.0
        np.testing.assert_allclose(np.asarray(w), expected, rtol=0, atol=1e-14)
        off = np.delete(np.asarray(w), i)
        assert np.all(off == 0.0), "off-diagonal weights must vanish exactly"


@pytest.mark.parametrize("tau", [-0.3, 0.1, 0.37, 0.9, 1.4])
def test_lagrange_weights_partition_of_unity_and_polynomials(tau):
    w = lagrange_weights(POINTS, jnp.asarray(tau, F64))
    assert w.shape == (len(POINTS),)
    assert float(jnp.sum(w)) == pytest.approx(1.0, abs=1e-13)
    x = np.asarray(POINTS)
    rng = np.random.default_rng(0)
    n = len(POINTS)
    for degree in range(n):
        coeffs = rng.normal(size=degree + 1)
        exact = np.polyval(coeffs, tau)
        assert float(w @ jnp.asarray(np.polyval(coeffs, x))) == pytest.approx(exact, abs=1e-12)
    # The nodal polynomial of degree n vanishes at every point but not at tau.
    nodal = lambda s: np.prod([s - xi for xi in x])
    assert float(w @ jnp.asarray([nodal(xi) for xi in x])) == 0.0
    assert abs(nodal(tau)) > 1e-4


def test_lagrange_weights_dtype_and_jit():
    w = jax.jit(lambda t: lagrange_weights(POINTS, t))(jnp.asarray(0.3, jnp.float32))
    assert w.dtype == jnp.float32
    assert float(jnp.sum(w)) == pytest.approx(1.0, abs=1e-5)


# -- 5. ShallowNetBasis ----------------------------------------------------------------------


def _theta(width, dim, seed=0, dtype=F64):
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.normal(size=(3 * width, dim)), dtype)


def _by_hand(activation, theta, width, tau):
    theta = np.asarray(theta)
    alpha, w, beta = theta[:width], theta[width : 2 * width], theta[2 * width :]
    out = np.zeros(theta.shape[1])
    for d in range(theta.shape[1]):
        for i in range(width):
            out[d] += alpha[i, d] * float(activation(jnp.asarray(w[i, d] * tau + beta[i, d])))
    return out


@pytest.mark.parametrize("activation", [dvi.tanh, dvi.sin, dvi.relu_k(3)], ids=activation_name)
def test_shallow_evaluate_matches_hand_sum(activation):
    width, dim = 4, 3
    basis = dvi.ShallowNetBasis(activation, width)
    theta = _theta(width, dim)
    assert basis.num_params() == 3 * width
    for tau in (0.0, 0.3, 1.0, 1.7):
        got = basis.evaluate(theta, jnp.asarray(tau, F64))
        assert got.shape == (dim,)
        np.testing.assert_allclose(
            np.asarray(got), _by_hand(activation, theta, width, tau), rtol=1e-13, atol=1e-14
        )


def test_shallow_split_join_roundtrip():
    basis = dvi.ShallowNetBasis(dvi.tanh, 5)
    theta = _theta(5, 2)
    alpha, w, beta = basis.split(theta)
    assert alpha.shape == w.shape == beta.shape == (5, 2)
    np.testing.assert_array_equal(basis.join(alpha, w, beta), theta)


@pytest.mark.parametrize("activation", [dvi.tanh, dvi.gelu, dvi.relu_k(3)], ids=activation_name)
def test_shallow_value_and_derivative_matches_finite_differences(activation):
    basis = dvi.ShallowNetBasis(activation, 6)
    theta = _theta(6, 2, seed=1)
    step = 1e-5
    for tau in (0.1, 0.5, 0.9):
        q, dq = basis.value_and_derivative(theta, tau)
        np.testing.assert_allclose(q, basis.evaluate(theta, jnp.asarray(tau, F64)), rtol=1e-15)
        plus = basis.evaluate(theta, jnp.asarray(tau + step, F64))
        minus = basis.evaluate(theta, jnp.asarray(tau - step, F64))
        fd = (plus - minus) / (2 * step)
        np.testing.assert_allclose(np.asarray(dq), np.asarray(fd), rtol=1e-7, atol=1e-8)
        assert dq.dtype == F64


@pytest.mark.parametrize("activation", [dvi.tanh, dvi.sigmoid, dvi.relu_k(3)], ids=activation_name)
@pytest.mark.parametrize("ratio", [1.0, 0.5, 2.0, 0.37])
def test_shallow_advance_continues_the_curve(activation, ratio):
    basis = dvi.ShallowNetBasis(activation, 5)
    theta = _theta(5, 2, seed=2)
    advanced = basis.advance(theta, jnp.asarray(ratio, F64))
    assert advanced.shape == theta.shape
    for tau in (0.0, 0.25, 0.6, 1.0):
        lhs = basis.evaluate(advanced, jnp.asarray(tau, F64))
        rhs = basis.evaluate(theta, jnp.asarray(1.0 + ratio * tau, F64))
        np.testing.assert_allclose(np.asarray(lhs), np.asarray(rhs), rtol=1e-13, atol=1e-14)


def test_shallow_refuses_bad_arguments():
    with pytest.raises(ValueError, match="width"):
        dvi.ShallowNetBasis(dvi.tanh, 0)
    with pytest.raises(TypeError, match="callable"):
        dvi.ShallowNetBasis(3.0, 4)


# -- 6. formulation --------------------------------------------------------------------------


def lagrangian(t, q, v, args):
    """Time dependent, position-dependent mass, magnetic term and a potential (D = 2)."""
    mass = 1.0 + 0.3 * jnp.sin(q[0]) ** 2 + 0.1 * t
    magnetic = 0.4 * q[1] * v[0] - 0.2 * q[0] * v[1]
    return 0.5 * mass * v[0] ** 2 + 0.5 * v[1] ** 2 + magnetic - jnp.cos(q[0]) * (1 + q[1] ** 2)


def _context(quad_nodes=5):
    term = LagrangianTerm(lagrangian)
    basis = dvi.ShallowNetBasis(dvi.tanh, 4)
    nodes, weights = GaussLegendre(quad_nodes).nodes_weights(F64)
    return StepContext(
        term=term,
        basis=basis,
        t=jnp.asarray(0.7, F64),
        h=jnp.asarray(0.3, F64),
        q0=jnp.asarray([0.4, -0.2], F64),
        p0=jnp.asarray([0.1, 0.5], F64),
        args=None,
        nodes=nodes,
        weights=weights,
    )


def _discrete_action(ctx, theta, curve=None):
    if curve is None:

        def curve(tau):
            return ctx.basis.evaluate(theta, tau)

    total = jnp.zeros((), F64)
    for c, b in zip(ctx.nodes, ctx.weights, strict=True):
        q = curve(c)
        dq = jax.jacfwd(curve)(c)
        total = total + b * lagrangian(ctx.t + c * ctx.h, q, dq / ctx.h, None)
    return ctx.h * total


def test_stage_values_match_basis():
    ctx = _context()
    theta = _theta(4, 2, seed=3)
    q, dq = stage_values(lambda s: ctx.basis.evaluate(theta, s), ctx.nodes)
    assert q.shape == dq.shape == (5, 2)
    for j, c in enumerate(ctx.nodes):
        np.testing.assert_allclose(q[j], ctx.basis.evaluate(theta, c), rtol=1e-15)
        np.testing.assert_allclose(
            dq[j], jax.jacfwd(lambda s: ctx.basis.evaluate(theta, s))(c), rtol=1e-13
        )


@pytest.mark.parametrize("seed", [3, 4])
def test_action_gradient_is_grad_of_discrete_action(seed):
    ctx = _context()
    theta = _theta(4, 2, seed=seed)
    expected = jax.jit(jax.grad(lambda th: _discrete_action(ctx, th)))(theta)
    got = jax.jit(lambda th: action_gradient(ctx, ctx.basis.evaluate, th))(theta)
    assert got.shape == theta.shape
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-12, atol=1e-13)
    assert float(jnp.max(jnp.abs(expected))) > 1e-2  # not a trivially zero comparison


def test_free_endpoints_residual():
    ctx = _context()
    theta = _theta(4, 2, seed=5)
    p1 = jnp.asarray([0.3, -0.8], F64)
    r_theta, r_cont = jax.jit(lambda x: FreeEndpoints().residual(x, ctx))((theta, p1))
    assert r_theta.shape == theta.shape and r_cont.shape == ctx.q0.shape
    zero, one = jnp.zeros((), F64), jnp.ones((), F64)
    np.testing.assert_allclose(
        np.asarray(r_cont), np.asarray(ctx.q0 - ctx.basis.evaluate(theta, zero)), rtol=1e-15
    )

    def boundary_minus_action(th):
        ends = p1 @ ctx.basis.evaluate(th, one) - ctx.p0 @ ctx.basis.evaluate(th, zero)
        return ends - _discrete_action(ctx, th)

    expected = jax.jit(jax.grad(boundary_minus_action))(theta)
    np.testing.assert_allclose(np.asarray(r_theta), np.asarray(expected), rtol=1e-12, atol=1e-13)

    q1, p_end = FreeEndpoints().end_state((theta, p1), ctx)
    np.testing.assert_allclose(q1, ctx.basis.evaluate(theta, one), rtol=1e-15)
    np.testing.assert_array_equal(p_end, p1)


def test_interpolating_endpoints_residual_and_end_momentum():
    ctx = _context()
    theta = _theta(4, 2, seed=6)
    q1 = jnp.asarray([0.45, -0.1], F64)
    form = InterpolatingEndpoints()

    def action(th, a, b):
        return _discrete_action(ctx, th, lambda tau: form.position(ctx.basis, th, a, b, tau))

    g_theta, g_q0, g_q1 = jax.jit(jax.grad(action, argnums=(0, 1, 2)))(theta, ctx.q0, q1)
    r_theta, r_q = jax.jit(lambda x: form.residual(x, ctx))((theta, q1))
    np.testing.assert_allclose(np.asarray(r_theta), np.asarray(g_theta), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(np.asarray(r_q), np.asarray(ctx.p0 + g_q0), rtol=1e-12, atol=1e-13)
    q_end, p_end = form.end_state((theta, q1), ctx)
    np.testing.assert_array_equal(q_end, q1)
    np.testing.assert_allclose(np.asarray(p_end), np.asarray(g_q1), rtol=1e-12, atol=1e-13)
    # The curve passes through both ends for any parameters.
    np.testing.assert_allclose(form.position(ctx.basis, theta, ctx.q0, q1, 0.0), ctx.q0)
    np.testing.assert_allclose(form.position(ctx.basis, theta, ctx.q0, q1, 1.0), q1)


# -- 7. implicit midpoint seed ---------------------------------------------------------------


def oscillator(t, q, v, args):
    return jnp.sum(0.5 * v**2 - 0.5 * q**2)


def _midpoint(term, t, h, q0, p0, substeps, iterations=3, dtype=F64):
    return implicit_midpoint(
        term,
        jnp.asarray(t, dtype),
        jnp.asarray(h, dtype),
        jnp.asarray(q0, dtype),
        jnp.asarray(p0, dtype),
        None,
        substeps,
        iterations,
    )


def test_implicit_midpoint_second_order_on_oscillator():
    term = LagrangianTerm(oscillator)
    q0, p0, h = 0.5, 0.3, 1.0
    q_exact = q0 * math.cos(h) + p0 * math.sin(h)
    p_exact = p0 * math.cos(h) - q0 * math.sin(h)
    errors_q, errors_p = [], []
    for n in (4, 8, 16, 32):
        qs, p_end = _midpoint(term, 0.0, h, [q0], [p0], n)
        assert qs.shape == (n + 1, 1)
        assert float(qs[0, 0]) == q0
        errors_q.append(abs(float(qs[-1, 0]) - q_exact))
        errors_p.append(abs(float(p_end[0]) - p_exact))
    for errors in (errors_q, errors_p):
        for e0, e1 in zip(errors, errors[1:], strict=False):
            assert 3.5 < e0 / e1 < 4.5, errors
    assert errors_q[-1] < 1e-4


def test_implicit_midpoint_intermediate_labels_on_grid():
    term = LagrangianTerm(oscillator)
    n, h = 64, 0.8
    qs, _ = _midpoint(term, 0.0, h, [1.0], [0.0], n)
    exact = np.cos(h * np.arange(n + 1) / n)
    np.testing.assert_allclose(np.asarray(qs[:, 0]), exact, atol=1e-4)


def test_implicit_midpoint_degenerate_pendulum():
    problem = problems.pendulum()
    q0, p0 = problem.y0
    h, n = 0.5, 10
    qs, p_end = _midpoint(problem.term, problem.t0, h, q0, p0, n, iterations=4)
    assert qs.shape == (n + 1, 2)
    assert bool(jnp.all(jnp.isfinite(qs))) and bool(jnp.all(jnp.isfinite(p_end)))
    q_ref, p_ref = problem.reference(np.asarray([problem.t0 + h]))
    np.testing.assert_allclose(np.asarray(qs[-1]), q_ref[0], atol=1e-3)
    np.testing.assert_allclose(np.asarray(p_end), p_ref[0], atol=1e-3)
    # The constraint p₂ = 0 of the degenerate Lagrangian is kept (f₂ vanishes at the midpoint).
    assert abs(float(p_end[1])) < 1e-12
    # And it converges with the second order of the midpoint rule.
    qs2, _ = _midpoint(problem.term, problem.t0, h, q0, p0, 2 * n, iterations=4)
    e1 = np.max(np.abs(np.asarray(qs[-1]) - q_ref[0]))
    e2 = np.max(np.abs(np.asarray(qs2[-1]) - q_ref[0]))
    assert 3.0 < e1 / e2 < 5.0


def time_dependent(t, q, v, args):
    return jnp.sum(0.5 * v**2 - 0.5 * q**2 * (1 + t))


def test_implicit_midpoint_starts_at_given_time():
    term = LagrangianTerm(time_dependent)
    at0 = _midpoint(term, 0.0, 0.5, [0.5], [0.2], 8)
    at5 = _midpoint(term, 5.0, 0.5, [0.5], [0.2], 8)
    assert abs(float(at0[0][-1, 0]) - float(at5[0][-1, 0])) > 1e-3
    # Starting at t = 5 is the same as starting at 0 with the Lagrangian shifted by 5.
    shifted = LagrangianTerm(lambda t, q, v, args: time_dependent(t + 5.0, q, v, args))
    ref = _midpoint(shifted, 0.0, 0.5, [0.5], [0.2], 8)
    np.testing.assert_allclose(np.asarray(at5[0]), np.asarray(ref[0]), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(np.asarray(at5[1]), np.asarray(ref[1]), rtol=1e-13, atol=1e-15)


def test_implicit_midpoint_float32():
    term = LagrangianTerm(oscillator)
    qs, p_end = _midpoint(term, 0.0, 1.0, [0.5], [0.3], 8, dtype=jnp.float32)
    assert qs.dtype == jnp.float32 and p_end.dtype == jnp.float32
    assert abs(float(qs[-1, 0]) - (0.5 * math.cos(1.0) + 0.3 * math.sin(1.0))) < 1e-2


def test_implicit_midpoint_iode_oscillator_matches_lagrangian():
    iode = IODETerm(lambda t, q, v, a: v, lambda t, q, v, a: -q)
    lag = LagrangianTerm(oscillator)
    a = _midpoint(iode, 0.0, 1.0, [0.5], [0.3], 6)
    b = _midpoint(lag, 0.0, 1.0, [0.5], [0.3], 6)
    np.testing.assert_allclose(np.asarray(a[0]), np.asarray(b[0]), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(a[1]), np.asarray(b[1]), rtol=1e-14)


# -- the Jacobian by coordinate blocks (`jacobian="structured"`) ------------------------------
STRUCTURED_CASES = [
    ("harmonic_oscillator", dvi.ShallowNetBasis(dvi.tanh, 6), 8),
    ("double_pendulum", dvi.ShallowNetBasis(dvi.gelu, 5), 6),
    ("pendulum", dvi.ShallowNetBasis(dvi.tanh, 4, symmetry=dvi.MirrorPairs()), 8),
    ("toda_lattice", dvi.ShallowNetBasis(dvi.tanh, 3), 4),
    ("kepler", dvi.LagrangeBasis(4), 5),
]


@pytest.mark.parametrize("name,basis,nodes", STRUCTURED_CASES, ids=[c[0] for c in STRUCTURED_CASES])
def test_structured_jacobian_matches_autodiff(name, basis, nodes):
    from jax.flatten_util import ravel_pytree

    problem = getattr(problems, name)(dtype=F64)
    seed = {} if isinstance(basis, dvi.ShallowNetBasis) else dict(initial_guess=LeastSquaresFit())
    solver = dvi.NetworkVI(basis, GaussLegendre(nodes), **seed)
    ctx = solver._context(problem.term, 0.3, 0.45, problem.y0, problem.args)
    dim = ctx.q0.shape[0]
    theta = 0.5 * jax.random.normal(jax.random.PRNGKey(1), (basis.num_params(), dim), F64)
    x = (theta, ctx.p0 + 0.1)
    flat, unravel = ravel_pytree(x)
    form = FreeEndpoints()
    dense = jax.jit(jax.jacfwd(lambda v: ravel_pytree(form.residual(unravel(v), ctx))[0]))(flat)
    blocks = jax.jit(lambda v: form.jacobian(unravel(v), ctx))(flat)
    assert blocks.shape == dense.shape and blocks.dtype == F64
    np.testing.assert_allclose(blocks, dense, rtol=0, atol=1e-14 * float(jnp.max(jnp.abs(dense))))
    # formulations / bases without the block form say so
    assert InterpolatingEndpoints().jacobian(x, ctx) is None


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float16], ids=lambda d: d.__name__)
def test_structured_jacobian_keeps_the_working_dtype(dtype):
    problem = problems.double_pendulum(dtype=dtype)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 3), GaussLegendre(4))
    ctx = solver._context(problem.term, dtype(0.0), dtype(0.1), problem.y0, problem.args)
    theta = jnp.full((solver.basis.num_params(), 2), 0.3, dtype)
    fn = lambda th: FreeEndpoints().jacobian((th, ctx.p0), ctx)
    assert jax.jit(fn)(theta).dtype == dtype
    assert "f64" not in str(jax.make_jaxpr(fn)(theta))


def test_structured_jacobian_needs_the_callers_matrix():
    with pytest.raises(ValueError, match="options\\['jacobian'\\]"):
        _find(well_posed, LevenbergMarquardt(jacobian="structured"), jnp.zeros(10, F64))
    given = lambda y, args: jax.jacfwd(lambda v: well_posed(v, args))(y)
    sol = _find(well_posed, LevenbergMarquardt(jacobian="structured"), jnp.zeros(10, F64),
                options=dict(jacobian=given))
    assert sol.result == optx.RESULTS.successful
    assert float(jnp.max(jnp.abs(sol.value - _XSTAR))) <= 1e-13
    with pytest.raises(ValueError, match="jacobian must be"):
        LevenbergMarquardt(jacobian="blocks")


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32, jnp.float16])
def test_damped_least_squares_solves_the_regularised_problem(dtype):
    """`d = argmin ‖J d − r‖² + μ‖d‖²`, also for a singular `J`, against the normal equations
    solved in float64, and in the dtype of the right-hand side."""
    from diffrax_vi.linalg import damped_least_squares

    rng = np.random.default_rng(3)
    jac = rng.standard_normal((12, 12))
    jac[:, -1] = jac[:, 0]  # rank-deficient, as the network steps are
    rhs = rng.standard_normal(12)
    mu = 1e-2
    expected = np.linalg.solve(jac.T @ jac + mu * np.eye(12), jac.T @ rhs)
    d = damped_least_squares(jnp.asarray(jac, dtype), jnp.asarray(rhs, dtype),
                             jnp.sqrt(jnp.asarray(mu, dtype)))
    assert d.dtype == dtype
    eps = float(jnp.finfo(dtype).eps)
    tol = 1e-10 if dtype == jnp.float64 else 300 * eps
    np.testing.assert_allclose(np.asarray(d, np.float64), expected, rtol=0,
                               atol=tol * np.max(np.abs(expected)))


@pytest.mark.parametrize("rows", [30, 12, 5, 2])
def test_damped_least_squares_takes_any_shape_and_several_right_hand_sides(rows):
    """Tall, square and wide matrices (the seed fits are tall, the Newton steps square), and a
    matrix of right-hand sides solved column by column, as the seed fits pass them (the
    right-hand sides ride along as columns of the factorised matrix)."""
    from diffrax_vi.linalg import damped_least_squares

    rng = np.random.default_rng(4)
    jac = rng.standard_normal((rows, 12))
    rhs = rng.standard_normal((rows, 3))
    mu = 0.3
    normal = jac.T @ jac + mu * np.eye(12)
    expected = np.linalg.solve(normal, jac.T @ rhs)
    d = damped_least_squares(jnp.asarray(jac), jnp.asarray(rhs), jnp.sqrt(mu))
    assert d.shape == (12, 3)
    np.testing.assert_allclose(np.asarray(d), expected, rtol=0, atol=1e-12)
    for j in range(3):
        one = damped_least_squares(jnp.asarray(jac), jnp.asarray(rhs[:, j]), jnp.sqrt(mu))
        assert one.shape == (12,)
        np.testing.assert_allclose(np.asarray(one), expected[:, j], rtol=0, atol=1e-12)


# -- closed-form network derivatives (`ShallowNetBasis.jet`) ----------------------------------
@pytest.mark.parametrize(
    "activation", [dvi.tanh, dvi.gelu, dvi.sin, dvi.sigmoid, dvi.relu_k(3)],
    ids=["tanh", "gelu", "sin", "sigmoid", "relu3"],
)
def test_network_jet_matches_autodiff(activation):
    """Values, slopes, their parameter gradients and a weighted Hessian of the network at a
    few points, against JAX differentiating `ShallowNetBasis.evaluate`."""
    basis = dvi.ShallowNetBasis(activation, 4)
    dim, taus = 3, jnp.array([0.0, 0.2, 0.7, 1.0], F64)
    theta = jax.random.normal(jax.random.PRNGKey(3), (basis.num_params(), dim), F64)
    u, v = jax.random.normal(jax.random.PRNGKey(4), (2, taus.size, dim), F64)
    jet = basis.jet(theta, taus)

    def curve(th_d, tau):
        return basis.evaluate(th_d[:, None], tau)[0]

    def slope(th_d, tau):
        return jax.grad(curve, argnums=1)(th_d, tau)

    def psi(th_d, u_d, v_d):
        return jnp.sum(u_d * jax.vmap(curve, (None, 0))(th_d, taus)
                       + v_d * jax.vmap(slope, (None, 0))(th_d, taus))

    per_point = jax.vmap(jax.vmap(curve, (1, None)), (None, 0))  # (K, D)
    per_point_slope = jax.vmap(jax.vmap(slope, (1, None)), (None, 0))
    q, dq = jet.values()
    np.testing.assert_allclose(q, per_point(theta, taus), rtol=0, atol=1e-14)
    np.testing.assert_allclose(dq, per_point_slope(theta, taus), rtol=0, atol=1e-13)
    grad_q, grad_dq = jet.gradients()
    want_q = jax.vmap(jax.vmap(jax.grad(curve), (1, None)), (None, 0))(theta, taus)
    want_dq = jax.vmap(jax.vmap(jax.grad(slope), (1, None)), (None, 0))(theta, taus)
    np.testing.assert_allclose(grad_q, want_q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(grad_dq, want_dq, rtol=0, atol=1e-13)
    hess = jet.weighted_hessian(u, v)
    want = jax.vmap(jax.hessian(psi), in_axes=(1, 1, 1))(theta, u, v)
    assert hess.shape == (dim, basis.num_params(), basis.num_params())
    np.testing.assert_allclose(hess, want, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(want))))


def test_network_jet_applies_only_where_its_formulas_hold():
    plain = dvi.ShallowNetBasis(dvi.tanh, 4)
    mirrored = dvi.ShallowNetBasis(dvi.tanh, 4, symmetry=dvi.MirrorPairs())
    assert plain.has_jet and not mirrored.has_jet
    assert mirrored.jet(jnp.zeros((mirrored.num_params(), 1)), jnp.zeros(2)) is None
    form = FreeEndpoints()
    assert form.has_closed_form_jacobian(plain)
    assert not form.has_closed_form_jacobian(mirrored)
    assert not form.has_closed_form_jacobian(dvi.LagrangeBasis(4))
    assert not InterpolatingEndpoints().has_closed_form_jacobian(plain)


def test_auto_jacobian_hands_the_closed_form_to_the_root_finder():
    """Under `jacobian="auto"` NetworkVI passes its block Jacobian exactly where
    it has a closed form, and the root finder differentiates otherwise."""
    from diffrax_vi.step_solve import jacobian_option as _jacobian_option

    problem = problems.double_pendulum(dtype=F64)
    auto, fwd = LevenbergMarquardt(jacobian="auto"), LevenbergMarquardt()
    assert fwd.jacobian == "fwd"  # the default
    for basis, closed in [
        (dvi.ShallowNetBasis(dvi.tanh, 4), True),
        (dvi.ShallowNetBasis(dvi.tanh, 4, symmetry=dvi.MirrorPairs()), False),
        (dvi.LagrangeBasis(4), False),
    ]:
        shallow = isinstance(basis, dvi.ShallowNetBasis)
        seed = {} if shallow else dict(initial_guess=LeastSquaresFit())
        solver = dvi.NetworkVI(basis, GaussLegendre(6), **seed)
        ctx = solver._context(problem.term, 0.0, 0.1, problem.y0, problem.args)
        assert (_jacobian_option(auto, FreeEndpoints(), ctx) is not None) == closed
        assert _jacobian_option(fwd, FreeEndpoints(), ctx) is None
        structured = LevenbergMarquardt(jacobian="structured")
        assert _jacobian_option(structured, FreeEndpoints(), ctx) is not None


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
    """`options["start_at_fallback"]`: the solve begins at the fallback (the given point only
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
        _no_root_near_zero, solver, y, start, throw=False, max_steps=100, options=options))(
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
