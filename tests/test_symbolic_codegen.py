"""sympy → JAX compilation and the sympy derivative kernels of the network ansätze
(`diffrax_vi._codegen`, `diffrax_vi._ansatz.sympy_kernels`)."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy

import diffrax_vi as dvi
from diffrax_vi._ansatz.symmetry import MirrorPairs, SharedMirrorPairs
from diffrax_vi._ansatz.sympy_kernels import symbolic_dense_evaluate, symbolic_shallow_evaluate
from diffrax_vi._codegen import (
    compile_exprs,
    curve_function,
    symbolic_curve_evaluate,
    sympy_activation,
)

x, y = sympy.symbols("x y", real=True)

EXPRS = [
    sympy.Rational(1, 3) * x**2 + sympy.sqrt(y) * sympy.exp(x),
    sympy.erf(x) / y + sympy.pi,
    sympy.log(y) * sympy.sin(x) - sympy.cos(x * y) ** 3 + sympy.tan(x / 2),
    sympy.tanh(x - y) / (1 + x**2),
    y ** sympy.Rational(3, 2) - x**-2 + y**0.3 + y**x,
    sympy.Max(0, x) ** 3 + sympy.Abs(x - y) * sympy.sign(x),
    sympy.Piecewise((x, x > 0), (sympy.exp(x) - 1, True)),
]


def _lambdified(exprs, *args):
    f = sympy.lambdify([x, y], exprs, modules=["scipy", "numpy"])
    return [np.broadcast_to(np.asarray(v, np.float64), np.broadcast(*args).shape) for v in f(*args)]


# -- compile_exprs ------------------------------------------------------------------------------


def test_compile_matches_sympy():
    xs = np.array([-1.3, -0.2, 0.4, 1.7])
    ys = np.array(0.8)
    f = compile_exprs(EXPRS, [x, y])
    out = f(jnp.asarray(xs), jnp.asarray(ys))
    assert len(out) == len(EXPRS)
    for got, want in zip(out, _lambdified(EXPRS, xs, ys), strict=True):
        assert got.shape == xs.shape
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-14, atol=1e-15)


def test_cse_on_and_off_agree_and_compile_once():
    f = compile_exprs(EXPRS, [x, y], cse=True)
    g = compile_exprs(EXPRS, [x, y], cse=False)
    assert "_s0" in f.source and "_s0" not in g.source
    args = (jnp.linspace(-1.0, 1.0, 7), jnp.asarray(0.6))
    for a, b in zip(f(*args), g(*args), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15, atol=1e-16)
    assert compile_exprs(list(EXPRS), (x, y), cse=True) is f


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_compile_keeps_dtype(dtype):
    f = compile_exprs(EXPRS + [sympy.Integer(2), sympy.pi * sympy.E], [x, y])
    out = f(jnp.asarray([0.3, 0.7], dtype), jnp.asarray(1.5, dtype))
    for o in out:
        assert o.dtype == dtype and o.shape == (2,)
    # Integer inputs give the default float.
    assert f(1, 2)[0].dtype == jnp.float64


def test_float32_trace_has_no_float64():
    f = compile_exprs(EXPRS, [x, y])
    jaxpr = jax.make_jaxpr(f)(jnp.float32(0.3), jnp.float32(1.5))
    assert "f64" not in str(jaxpr)
    # ... also through derivatives of a sympy-differentiated curve.
    tau = sympy.Symbol("tau", real=True)
    curve = curve_function(sympy.Rational(1, 7) * x * sympy.exp(y * tau) + sympy.pi, tau, [x, y])
    args = (jnp.float32(0.3), jnp.float32(1.5), jnp.float32(0.25))
    jaxpr = jax.make_jaxpr(jax.jacfwd(jax.grad(curve, argnums=(0, 1)), argnums=(0, 1, 2)))(*args)
    assert "f64" not in str(jaxpr)


def test_compile_errors():
    z = sympy.Symbol("z")
    with pytest.raises(ValueError, match="z"):
        compile_exprs([x + z], [x])
    f = sympy.Function("mystery")
    with pytest.raises(ValueError, match="mystery"):
        compile_exprs([f(x)], [x])
    with pytest.raises(ValueError, match="not a real number"):
        compile_exprs([x + sympy.I], [x])


# -- activations --------------------------------------------------------------------------------

ACTIVATIONS = [dvi.tanh, dvi.sigmoid, dvi.sin, dvi.gelu, dvi.elu, dvi.relu_k(3), dvi.relu_k(1)]


@pytest.mark.parametrize(
    "activation", ACTIVATIONS, ids=lambda a: dvi._activations.activation_name(a)
)
def test_sympy_activation_matches_jax(activation):
    s = sympy.Symbol("s", real=True)
    form = sympy_activation(activation)
    f = compile_exprs([form(s), sympy.diff(form(s), s)], [s])
    xs = jnp.linspace(-3.0, 3.0, 61)
    value, slope = f(xs)
    np.testing.assert_allclose(value, activation(xs), rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(slope, jax.vmap(jax.grad(activation))(xs), rtol=1e-14, atol=1e-15)


def test_sympy_activation_unknown():
    with pytest.raises(ValueError, match="no sympy form"):
        sympy_activation(lambda v: v**2)


# -- sympy derivative kernels against autodiff ---------------------------------------------------

NODES = jnp.array([0.0, 0.113, 0.5, 0.887, 1.0])


def _checks(autodiff_eval, sympy_eval, theta):
    """Value, jvp in τ (stage values), vjp in θ (action gradient) and the jacfwd of that
    (Newton Jacobian): the relative max deviation of sympy from autodiff for each."""

    def stages(evaluate):
        def fn(th):
            def one(t):
                return jax.jvp(lambda s: evaluate(th, s), (t,), (jnp.ones_like(t),))

            return jax.vmap(one)(NODES)

        return fn

    def gradient(evaluate):
        def fn(th):
            (q, dq), pullback = jax.vjp(stages(evaluate), th)
            return pullback((jnp.sin(3 * q), jnp.cos(dq)))[0]

        return fn

    maps = {
        "value": lambda ev: lambda th: ev(th, jnp.asarray(0.37, th.dtype)),
        "stages": stages,
        "gradient": gradient,
        "jacobian": lambda ev: jax.jacfwd(gradient(ev)),
    }
    errors = {}
    for name, make in maps.items():
        want = jax.tree_util.tree_leaves(jax.jit(make(autodiff_eval))(theta))
        got = jax.tree_util.tree_leaves(jax.jit(make(sympy_eval))(theta))
        errors[name] = max(
            float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(a)))
            for a, b in zip(want, got, strict=True)
        )
    return errors


@pytest.mark.parametrize(
    "basis",
    [
        dvi.ShallowNetBasis(dvi.tanh, 4),
        dvi.ShallowNetBasis(dvi.gelu, 4),
        dvi.ShallowNetBasis(dvi.relu_k(3), 4),
        dvi.ShallowNetBasis(dvi.tanh, 4, symmetry=MirrorPairs()),
        dvi.ShallowNetBasis(dvi.sigmoid, 4, symmetry=SharedMirrorPairs()),
    ],
    ids=repr,
)
def test_shallow_sympy_derivatives_match_autodiff(basis):
    theta = jax.random.normal(jax.random.PRNGKey(3), (basis.num_params(), 2))
    errors = _checks(basis.evaluate, symbolic_shallow_evaluate(basis), theta)
    assert max(errors.values()) < 1e-13, errors


def test_shallow_sympy_uses_custom_jvp_and_keeps_float32():
    basis = dvi.ShallowNetBasis(dvi.tanh, 3)
    evaluate = symbolic_shallow_evaluate(basis)
    theta = jax.random.normal(jax.random.PRNGKey(0), (9, 2), jnp.float32)
    tau = jnp.float32(0.3)
    jaxpr = str(
        jax.make_jaxpr(lambda th: jax.jvp(lambda s: evaluate(th, s), (tau,), (tau,)))(theta)
    )
    assert "custom_jvp_call" in jaxpr and "f64" not in jaxpr
    q, dq = jax.jvp(lambda s: evaluate(theta, s), (tau,), (jnp.ones_like(tau),))
    assert q.dtype == dq.dtype == jnp.float32 and q.shape == (2,)


def test_dense_sympy_derivatives_match_autodiff():
    from diffrax_vi._ansatz.dense import DenseNetBasis

    basis = DenseNetBasis(dvi.tanh, 3, 2)
    theta = 0.7 * jax.random.normal(jax.random.PRNGKey(5), (basis.num_params(), 2))
    errors = _checks(basis.evaluate, symbolic_dense_evaluate(basis), theta)
    assert max(errors.values()) < 1e-13, errors


def test_generic_curve_evaluate():
    tau = sympy.Symbol("tau", real=True)
    a, b, c = sympy.symbols("a b c", real=True)
    evaluate = symbolic_curve_evaluate(a * sympy.exp(-b * tau) * sympy.sin(c * tau), tau, [a, b, c])

    def autodiff(theta, s):
        return theta[0] * jnp.exp(-theta[1] * s) * jnp.sin(theta[2] * s)

    theta = jax.random.normal(jax.random.PRNGKey(2), (3, 2))
    errors = _checks(autodiff, evaluate, theta)
    assert max(errors.values()) < 1e-13, errors
    # Second τ-derivative via the velocity's custom rule.
    second = jax.grad(jax.grad(lambda s: evaluate(theta, s)[0]))(0.4)
    want = jax.grad(jax.grad(lambda s: autodiff(theta, s)[0]))(0.4)
    np.testing.assert_allclose(second, want, rtol=1e-13)
