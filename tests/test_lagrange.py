"""Lagrange weights through fixed points (`diffrax_vi.lagrange`)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffrax_vi.lagrange import lagrange_weights

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
