"""The quadrature rules (`diffrax_vi._quadrature`): exactness, dtypes and refused counts of
`GaussLegendre` and `Simpson`; Gauss–Legendre and Gauss–Lobatto coefficients computed in
extended precision, rounded once to the working dtype, with their symmetries exact in that
dtype (issue 28)."""

import jax

jax.config.update("jax_enable_x64", True)

import itertools  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from fractions import Fraction  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import mpmath  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from diffrax_vi import _quadrature as quadrature  # noqa: E402
from diffrax_vi._ansatz.polynomial import lobatto_points  # noqa: E402
from diffrax_vi._quadrature import GaussLegendre, Simpson  # noqa: E402

F64 = jnp.float64
NS = range(1, 33)
DTYPES = [np.float64, np.float32, np.float16]


def exact_rule(n):
    """All nodes and weights on [0, 1] in extended precision, increasing nodes."""
    nodes, weights = quadrature.gauss_legendre_exact(n)
    odd = n % 2
    return ([1 - c for c in reversed(nodes[odd:])] + list(nodes),
            list(reversed(weights[odd:])) + list(weights))


def spacing(x, dtype):
    """The spacing of `dtype` at the positive mpmath number `x`, as an mpmath number."""
    shift, _, _ = quadrature._split(x, dtype)
    return mpmath.ldexp(1, shift)


def error_in_ulps(value, x, dtype):
    with mpmath.workprec(256):
        return abs(mpmath.mpf(float(value)) - x) / spacing(x, dtype)


# -- the extended-precision values ----------------------------------------------------------


@pytest.mark.parametrize("n", [3, 6, 12, 24, 48])
def test_extended_values_match_mpmaths_own_gauss_legendre(n):
    # mpmath's quadrature module builds rules of 3·2^(m-1) nodes by its own method.
    with mpmath.workprec(256):
        rule = mpmath.calculus.quadrature.GaussLegendre(mpmath.mp)
        m = int(math.log2(n // 3)) + 1
        theirs = sorted(((1 + x) / 2, w / 2) for x, w in rule.calc_nodes(m, 256))
        c, b = exact_rule(n)
        assert len(theirs) == n
        for (x, w), ci, bi in zip(theirs, c, b, strict=True):
            assert abs(x - ci) < mpmath.mpf(10) ** -70
            assert abs(w - bi) < mpmath.mpf(10) ** -70


@pytest.mark.parametrize("n", NS)
def test_extended_values_integrate_the_moments_exactly(n):
    # n nodes and weights that integrate x^0 .. x^(2n-1) exactly are the Gauss rule.
    with mpmath.workprec(256):
        c, b = exact_rule(n)
        for k in range(2 * n):
            moment = mpmath.fsum(bi * ci**k for ci, bi in zip(c, b, strict=True))
            assert abs(moment - mpmath.mpf(1) / (k + 1)) < mpmath.mpf(10) ** -60, k


# -- rounding ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", NS)
def test_symmetries_exact_in_the_dtype(n, dtype):
    c, b = GaussLegendre(n).nodes_weights(dtype)
    assert c.dtype == b.dtype == jnp.dtype(dtype)
    c, b = np.asarray(c), np.asarray(b)  # arithmetic below stays in the dtype
    one = dtype(1)
    assert np.all(c + c[::-1] == one), "nodes not symmetric about 1/2"
    assert np.all(one - c == c[::-1])
    assert np.all(b == b[::-1]), "weights not equal in pairs"
    if n % 2:
        assert c[n // 2] == 0.5
    assert np.all(np.diff(c) > 0) and np.all(b > 0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", NS)
def test_weights_within_one_ulp_and_nodes_rounded_from_extended_precision(n, dtype):
    c, b = (np.asarray(a) for a in GaussLegendre(n).nodes_weights(dtype))
    c_ex, b_ex = exact_rule(n)
    for value, x in zip(b, b_ex, strict=True):
        assert error_in_ulps(value, x, dtype) < 1
    # The nodes above 1/2 are the nearest numbers of the dtype to the true nodes (rounded
    # once, not via float64); those below are their exact mirror images, so their error is
    # at most half a unit of the partner.
    for value, x in zip(c[(n + 1) // 2:], c_ex[(n + 1) // 2:], strict=True):
        assert error_in_ulps(value, x, dtype) <= 0.5
    for value, x in zip(c[: n // 2], c_ex[: n // 2], strict=True):
        with mpmath.workprec(256):
            assert abs(mpmath.mpf(float(value)) - x) <= spacing(1 - x, dtype) / 2


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", NS)
def test_weights_sum_rounds_to_one(n, dtype):
    _, b = GaussLegendre(n).nodes_weights(dtype)
    total = sum((Fraction(float(v)) for v in np.asarray(b)), Fraction(0))
    # The exact sum of the stored weights rounds to 1 in the dtype: it is closer to 1 than
    # half the spacing just below 1.
    assert abs(total - 1) < Fraction(1, 2) * Fraction(2) ** -(np.finfo(dtype).nmant + 1)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("n", range(1, 17))
def test_weights_sum_is_the_closest_to_one_the_rounding_allows(n, dtype):
    # Against every choice of rounding down or up per weight pair (each within one ulp).
    _, b_ex = exact_rule(n)
    upper = b_ex[n // 2:]
    mult = [1] * (n % 2) + [2] * (n // 2)
    choices = []
    for x in upper:
        shift, k, rest = quadrature._split(x, np.dtype(dtype))
        unit = Fraction(2) ** shift
        choices.append([k * unit] if rest == 0 else [k * unit, (k + 1) * unit])
    best = min(
        abs(sum((m * v for m, v in zip(mult, pick, strict=True)), Fraction(0)) - 1)
        for pick in itertools.product(*choices)
    )
    _, b = GaussLegendre(n).nodes_weights(dtype)
    total = sum((Fraction(float(v)) for v in np.asarray(b)), Fraction(0))
    assert abs(total - 1) == best


@pytest.mark.parametrize("n", NS)
def test_float64_rule_exact_for_polynomials_up_to_degree_2n_minus_1(n):
    c, b = (np.asarray(a) for a in GaussLegendre(n).nodes_weights(np.float64))
    u = 2.0**-53
    for k in range(2 * n):
        integral = math.fsum(b * c**k)
        # A priori bound: rounding in c**k and in the sum, relative (k + n + 2) u; weights
        # within one ulp, relative u; nodes within 2^-54 absolute, which moves the integral
        # by at most 2^-54 · ∫ k x^(k-1) dx = 2^-54.
        bound = (k + n + 3) * u / (k + 1) + 2.0**-54
        assert abs(integral - 1 / (k + 1)) <= bound, k


def test_results_are_cached_and_read_only():
    c1, b1 = GaussLegendre(9).nodes_weights_np()
    c2, b2 = GaussLegendre(9).nodes_weights_np()
    assert c1 is c2 and b1 is b2
    assert not c1.flags.writeable and not b1.flags.writeable
    single = quadrature._gauss_legendre(9, "float32")
    assert single[0] is quadrature._gauss_legendre(9, "float32")[0]


def test_other_dtypes_fall_back_to_the_float64_values():
    c, b = GaussLegendre(4).nodes_weights(jnp.bfloat16)
    assert c.dtype == jnp.bfloat16 and b.dtype == jnp.bfloat16
    assert abs(float(jnp.sum(b.astype(jnp.float64))) - 1) < 1e-2


def test_importing_the_package_does_not_import_mpmath():
    code = "import sys, diffrax_vi; print('mpmath' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# -- Gauss–Lobatto points of the Lagrange basis ----------------------------------------------


@pytest.mark.parametrize("degree", range(1, 25))
def test_lobatto_points_symmetric_and_roots_of_the_legendre_derivative(degree):
    pts = np.array(lobatto_points(degree))
    assert pts.dtype == np.float64 and len(pts) == degree + 1
    assert pts[0] == 0.0 and pts[-1] == 1.0
    assert np.all(pts + pts[::-1] == 1.0) and np.all(np.diff(pts) > 0)
    upper = quadrature.gauss_lobatto_upper(degree)
    with mpmath.workprec(256):
        for x in upper:
            # P'_s(y) = s (y P_s(y) − P_{s−1}(y)) / (y² − 1), with mpmath's own Legendre.
            y = 2 * x - 1
            slope = degree * (y * mpmath.legendre(degree, y) - mpmath.legendre(degree - 1, y))
            assert abs(slope) < mpmath.mpf(10) ** -60
        for value, x in zip(pts[len(pts) - len(upper) - 1: -1], upper, strict=True):
            assert error_in_ulps(value, x, np.float64) <= 0.5


def _integrate(rule, f):
    c, b = rule.nodes_weights(F64)
    return float(jnp.sum(b * f(c)))


# -- the rules in the working dtype ----------------------------------------------------------------


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
