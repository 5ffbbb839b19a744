"""sympy → JAX compilation, sympy derivative kernels of the network ansätze, and VISE."""

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi.oga.symmetry import MirrorPairs, SharedMirrorPairs
from diffrax_vi.seeding.fit import InitialWeights, fit_problem
from diffrax_vi.symbolic import (
    compile_exprs,
    curve_function,
    symbolic_curve_evaluate,
    symbolic_dense_evaluate,
    symbolic_shallow_evaluate,
    sympy_activation,
)
from diffrax_vi.symbolic.ansatz import SymbolicAnsatz, VISEBasis

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
    "activation", ACTIVATIONS, ids=lambda a: dvi.activations.activation_name(a)
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
    from diffrax_vi.ansatz.dense import DenseNetBasis

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


# -- SymbolicAnsatz -----------------------------------------------------------------------------

t = sympy.Symbol("t")
W1, W2, W3 = sympy.symbols("W1 W2 W3")


def test_symbolic_ansatz_interface():
    V1, V2 = sympy.symbols("V1 V2")
    basis = SymbolicAnsatz(
        [W1 * sympy.cos(W2 * t + W3), V1 * t**2 + V2], [[W1, W2, W3], [V1, V2]], t
    )
    assert VISEBasis is SymbolicAnsatz
    assert hash(basis) == hash(SymbolicAnsatz(list(basis.exprs), basis.weights, t))
    theta = basis.params_from(((0.5, 2.0, 0.1), (1.5, -1.0)), jnp.float64)
    assert [w.shape for w in theta] == [(3,), (2,)]
    assert [w.shape for w in basis.zeros(2, jnp.float32)] == [(3,), (2,)]
    assert basis.num_params() == 5

    bound = basis.at_step(jnp.asarray(1.2), jnp.asarray(0.5))
    q, dq = bound.value_and_derivative(theta, 0.4)
    s = 1.2 + 0.4 * 0.5
    np.testing.assert_allclose(q, [0.5 * math.cos(2 * s + 0.1), 1.5 * s**2 - 1], rtol=1e-15)
    # dq/dτ = h dq/dt.
    np.testing.assert_allclose(
        dq, [-0.5 * 0.5 * 2 * math.sin(2 * s + 0.1), 0.5 * 3 * s], rtol=1e-14
    )
    # Unbound, the second argument is the absolute time.
    np.testing.assert_allclose(basis.evaluate(theta, s), q, rtol=1e-15)
    assert basis.advance(theta, 2.0) is theta
    # Single coordinate: a flat weight sequence and flat initial values are accepted.
    one = SymbolicAnsatz([W1 * t], [W1], t)
    assert one.weights == ((W1,),)
    assert one.params_from((2.0,), jnp.float64)[0].shape == (1,)


def test_symbolic_ansatz_refuses_bad_input():
    with pytest.raises(ValueError, match="Z"):
        SymbolicAnsatz([W1 * sympy.cos(sympy.Symbol("Z") * t)], [[W1]], t)
    with pytest.raises(ValueError, match="coordinate 0"):
        SymbolicAnsatz([W1 * t + W2, W2 * t], [[W1], [W2]], t)
    with pytest.raises(ValueError, match="2 expression"):
        SymbolicAnsatz([W1 * t, W2 * t], [[W1, W2]], t)
    with pytest.raises(ValueError, match="one weight sequence per coordinate"):
        SymbolicAnsatz([W1 * t], [[W1], [W2]], t)
    basis = SymbolicAnsatz([W1 * sympy.cos(W2 * t + W3)], [[W1, W2, W3]], t)
    with pytest.raises(ValueError, match="3 weights"):
        basis.params_from(((0.5, 1.0),), jnp.float64)
    with pytest.raises(ValueError, match="coordinate"):
        basis.zeros(2, jnp.float64)


def test_initial_weights_restart_rule():
    basis = SymbolicAnsatz([W1 * sympy.cos(W2 * t + W3)], [[W1, W2, W3]], t)
    seed = InitialWeights(init=((0.5, 0.7, 0.0),), restart_radius=1.0)
    targets = jnp.zeros((11, 1))
    init = np.array([0.5, 0.7, 0.0])

    def seeded(previous, fresh):
        problem = fit_problem(targets, False, (jnp.asarray(previous),), jnp.asarray(fresh))
        return np.asarray(seed.fit(basis, problem)[0])

    near, far = init + [0.3, -0.4, 0.5], init + [0.0, 0.0, 1.2]
    np.testing.assert_array_equal(seeded(near, True), init)  # first step: init
    np.testing.assert_array_equal(seeded(near, False), near)  # warm start
    np.testing.assert_array_equal(seeded(far, False), init)  # drifted: restart
    never = InitialWeights(init=((0.5, 0.7, 0.0),), restart_radius=None)
    problem = fit_problem(targets, False, (jnp.asarray(far),), jnp.asarray(False))
    np.testing.assert_array_equal(np.asarray(never.fit(basis, problem)[0]), far)


# -- VISE end to end ----------------------------------------------------------------------------


def test_vise_harmonic_oscillator():
    """The reference's VISE test: `W1 cos(W2 t + W3)` from the exact weights, GL4, 1 and 5
    steps of 0.1 (the first saved point is the 1-step result)."""
    basis = SymbolicAnsatz([W1 * sympy.cos(W2 * t + W3)], [[W1, W2, W3]], t)
    solver = dvi.NetworkVI(
        basis,
        dvi.GaussLegendre(4),
        initial_guess=InitialWeights(init=((0.5, math.sqrt(0.5), 0.0),)),
        initial_trajectory=dvi.IntegratorExtrapolation(),
    )
    problem = problems.harmonic_oscillator(t1=0.5)
    ts = jnp.array([0.1, 0.5])
    sol = eqx.filter_jit(
        lambda y0: diffrax.diffeqsolve(
            problem.term,
            solver,
            0.0,
            0.5,
            0.1,
            y0,
            args=problem.args,
            saveat=diffrax.SaveAt(ts=ts, dense=True, solver_state=True),
        )
    )(problem.y0)
    assert sol.result == diffrax.RESULTS.successful
    q_ref, p_ref = problem.reference(np.asarray(ts))
    assert np.max(np.abs(np.asarray(sol.ys[0]) - q_ref)) < 1e-12
    assert np.max(np.abs(np.asarray(sol.ys[1]) - p_ref)) < 1e-12
    assert int(sol.solver_state.steps) == 5
    # Dense output follows the converged cosine inside a step.
    q_mid, _ = sol.evaluate(0.25)
    assert abs(float(q_mid[0]) - 0.5 * math.cos(math.sqrt(0.5) * 0.25)) < 1e-12


def _henon_heiles_lagrangian(t, q, v, args):
    return 0.5 * jnp.sum(v**2) - 0.5 * jnp.sum(q**2) - (q[0] ** 2 * q[1] - q[1] ** 3 / 3)


def _henon_heiles_energy(q, p):
    q1, q2 = q[..., 0], q[..., 1]
    with np.errstate(invalid="ignore"):  # a failed run leaves NaN/inf states
        return 0.5 * np.sum(p**2, -1) + 0.5 * np.sum(q**2, -1) + q1**2 * q2 - q2**3 / 3


def _vise_henon_heiles(t1):
    """The reference's VISE setting (problems_and_benchmarks.md §1.5): `q₀ = p₀ = (0.1, 0.1)`,
    h = 2, 8-node Gauss–Legendre, `W1 cos(W2 t + W3) + W4` per coordinate from the documented
    weights, Newton without regularisation (the reference's `regularization_factor = 0`)."""
    weights = [sympy.symbols(f"A{d}_1:5") for d in range(2)]
    exprs = [w[0] * sympy.cos(w[1] * t + w[2]) + w[3] for w in weights]
    init = ((0.14831, 1.0, -0.64812, -0.018712), (0.14298, -0.97215, 0.7615, -0.0013983))
    solver = dvi.NetworkVI(
        SymbolicAnsatz(exprs, weights, t),
        dvi.GaussLegendre(8),
        initial_guess=InitialWeights(init=init),
        initial_trajectory=dvi.IntegratorExtrapolation(),
        root_finder=dvi.RegularisedNewton(lam=1e-12),
    )
    y0 = (jnp.array([0.1, 0.1]), jnp.array([0.1, 0.1]))
    ts = jnp.arange(2.0, t1 + 1.0, 2.0)
    sol = eqx.filter_jit(
        lambda y0: diffrax.diffeqsolve(
            dvi.LagrangianTerm(_henon_heiles_lagrangian),
            solver,
            0.0,
            t1,
            2.0,
            y0,
            saveat=diffrax.SaveAt(ts=ts),
            throw=False,
        )
    )(y0)
    h0 = _henon_heiles_energy(np.array([0.1, 0.1]), np.array([0.1, 0.1]))
    energy = _henon_heiles_energy(np.asarray(sol.ys[0]), np.asarray(sol.ys[1]))
    return sol, np.max(np.abs(energy - h0)) / h0


def test_vise_henon_heiles():
    # Over the first 8 steps every step converges; measured max relative energy error 2.0e-4.
    sol, energy_error = _vise_henon_heiles(16.0)
    assert sol.result == diffrax.RESULTS.successful
    assert energy_error < 1e-3
