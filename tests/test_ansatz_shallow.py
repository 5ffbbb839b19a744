"""`ShallowNetBasis` (`diffrax_vi._ansatz.shallow`): evaluation, parameter layout, derivatives,
`advance`, and its closed-form derivatives (`jet`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi._activations import activation_name
from diffrax_vi._step.formulation import FreeEndpoints, InterpolatingEndpoints
from tests.helpers import random_theta as _theta

F64 = jnp.float64


# -- 5. ShallowNetBasis ----------------------------------------------------------------------


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

# -- closed-form network derivatives (`ShallowNetBasis.jet`) ----------------------------------
@pytest.mark.parametrize(
    "activation", [dvi.tanh, dvi.gelu, dvi.sin, dvi.sigmoid, dvi.relu_k(3)],
    ids=["tanh", "gelu", "sin", "sigmoid", "relu3"],
)
def test_network_jet_matches_autodiff(activation):
    """Values, slopes, their parameter gradients and a weighted Hessian of the network at a
    few points, against JAX differentiating `ShallowNetBasis.evaluate` (both in one compiled
    program: op by op, its hundred small programs took most of the test's time)."""
    basis = dvi.ShallowNetBasis(activation, 4)
    dim, taus = 3, jnp.array([0.0, 0.2, 0.7, 1.0], F64)
    theta = jax.random.normal(jax.random.PRNGKey(3), (basis.num_params(), dim), F64)
    u, v = jax.random.normal(jax.random.PRNGKey(4), (2, taus.size, dim), F64)

    def curve(th_d, tau):
        return basis.evaluate(th_d[:, None], tau)[0]

    def slope(th_d, tau):
        return jax.grad(curve, argnums=1)(th_d, tau)

    def psi(th_d, u_d, v_d):
        return jnp.sum(u_d * jax.vmap(curve, (None, 0))(th_d, taus)
                       + v_d * jax.vmap(slope, (None, 0))(th_d, taus))

    @jax.jit
    def closed_form_and_autodiff(theta, u, v):
        jet = basis.jet(theta, taus)
        per_point = jax.vmap(jax.vmap(curve, (1, None)), (None, 0))  # (K, D)
        per_point_slope = jax.vmap(jax.vmap(slope, (1, None)), (None, 0))
        closed = (*jet.values(), *jet.gradients(), jet.weighted_hessian(u, v))
        autodiff = (
            per_point(theta, taus),
            per_point_slope(theta, taus),
            jax.vmap(jax.vmap(jax.grad(curve), (1, None)), (None, 0))(theta, taus),
            jax.vmap(jax.vmap(jax.grad(slope), (1, None)), (None, 0))(theta, taus),
            jax.vmap(jax.hessian(psi), in_axes=(1, 1, 1))(theta, u, v),
        )
        return closed, autodiff

    (q, dq, grad_q, grad_dq, hess), (want_q, want_dq, want_gq, want_gdq, want) = (
        closed_form_and_autodiff(theta, u, v))
    np.testing.assert_allclose(q, want_q, rtol=0, atol=1e-14)
    np.testing.assert_allclose(dq, want_dq, rtol=0, atol=1e-13)
    np.testing.assert_allclose(grad_q, want_gq, rtol=0, atol=1e-13)
    np.testing.assert_allclose(grad_dq, want_gdq, rtol=0, atol=1e-13)
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
