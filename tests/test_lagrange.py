"""Lagrange weights through fixed points (`diffrax_vi._lagrange`)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi._lagrange import lagrange_values_and_slopes, lagrange_weights

F64 = jnp.float64


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


@pytest.mark.parametrize("degree", [1, 3, 6, 10])
def test_a_curve_continued_is_the_same_polynomial(degree):
    # `advance` evaluates the Lagrange values at the next step's points as a polynomial in the
    # step ratio (constant coefficients): the same curve to rounding, in the curve's dtype.
    jax.config.update("jax_enable_x64", True)
    basis = dvi.LagrangeBasis(degree)
    theta = jnp.asarray(np.random.default_rng(degree).normal(size=(degree + 1, 2)))
    points = jnp.asarray(basis.control_points)
    for ratio in (1.0, 0.5, 1.7):
        continued = basis.advance(theta, ratio)
        direct = jax.vmap(lambda t: basis.evaluate(theta, t))(1 + ratio * points)
        scale = float(jnp.max(jnp.abs(direct)))
        assert float(jnp.max(jnp.abs(continued - direct))) <= 1e-14 * scale
    assert basis.advance(theta.astype(jnp.float32), 0.5).dtype == jnp.float32


def test_values_and_slopes_in_numpy_are_the_basis_and_its_derivative():
    jax.config.update("jax_enable_x64", True)
    taus = np.array([0.0, 0.1, 0.5, 0.9, 1.0, 1.3])
    values, slopes = lagrange_values_and_slopes(POINTS, taus)
    for i, tau in enumerate(taus):
        value, slope = jax.jvp(lambda t: lagrange_weights(POINTS, t), (jnp.asarray(tau, F64),),
                               (jnp.ones((), F64),))
        np.testing.assert_allclose(values[i], np.asarray(value), rtol=0, atol=1e-14)
        np.testing.assert_allclose(slopes[i], np.asarray(slope), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(values[0], np.eye(len(POINTS))[0])  # one-hot at a point
