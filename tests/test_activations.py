"""The activations (`diffrax_vi._activations`): dtypes, values, `relu_k` and the precision
check of user activations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi._activations import ReLUk, activation_name, check_activation

F64 = jnp.float64


# -- 2. activations --------------------------------------------------------------------------

ACTIVATIONS = [
    dvi.tanh, dvi.sigmoid, dvi.sin, dvi.gelu, dvi.gelu_exact, dvi.elu, dvi.relu_k(1), dvi.relu_k(3)
]


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
