"""JAX's own activation functions are the package's (issue 52): the same basis, the same default
step; and a network whose activation has no hidden-layer rule says that it falls back to the
all-parameter step."""

import functools
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._activations import package_activation

# (JAX's function, the package's activation it computes)
RECOGNISED = [
    (jnp.tanh, dvi.tanh),
    (jax.nn.tanh, dvi.tanh),
    (jax.lax.tanh, dvi.tanh),
    (jax.nn.sigmoid, dvi.sigmoid),
    (jax.lax.logistic, dvi.sigmoid),
    (jax.nn.gelu, dvi.gelu),
    (functools.partial(jax.nn.gelu, approximate=True), dvi.gelu),
    (functools.partial(jax.nn.gelu, approximate=False), dvi.gelu_exact),
    (jnp.sin, dvi.sin),
    (jax.lax.sin, dvi.sin),
    (jax.nn.elu, dvi.elu),
    (jax.nn.relu, dvi.relu_k(1)),
]


def _name(value):
    return getattr(value, "__name__", None) or repr(value).split(" ")[0]


@pytest.mark.parametrize(
    "jax_function, ours", RECOGNISED, ids=[f"{_name(j)}-{_name(o)}" for j, o in RECOGNISED]
)
def test_a_jax_function_becomes_the_package_activation(jax_function, ours):
    basis = dvi.ShallowNetBasis(jax_function, 6)
    assert basis.activation is ours or basis.activation == ours
    assert basis == dvi.ShallowNetBasis(ours, 6)
    assert hash(basis) == hash(dvi.ShallowNetBasis(ours, 6))
    assert repr(basis) == repr(dvi.ShallowNetBasis(ours, 6))
    x = jnp.linspace(-3.0, 3.0, 13, dtype=jnp.float64)
    np.testing.assert_array_equal(np.asarray(ours(x)), np.asarray(jax_function(x)))


def test_the_repr_names_the_activation_a_jax_function_became():
    assert repr(dvi.ShallowNetBasis(jax.nn.relu, 4)) == "ShallowNetBasis(relu_k(1), width=4)"
    gelu_erf = functools.partial(jax.nn.gelu, approximate=False)
    assert repr(dvi.ShallowNetBasis(gelu_erf, 4)) == "ShallowNetBasis(gelu_exact, width=4)"
    assert repr(dvi.ShallowNetBasis(jnp.tanh, 4)) == "ShallowNetBasis(tanh, width=4)"


def test_other_functions_stay_as_they_are():
    own = lambda x: jnp.tanh(x) ** 3  # noqa: E731
    for activation in (own, jax.nn.silu, functools.partial(jax.nn.gelu, 1.0),
                       functools.partial(jax.nn.elu, alpha=2.0)):
        assert package_activation(activation) is activation
        assert dvi.ShallowNetBasis(activation, 4).activation is activation


def test_gelu_exact_is_jax_exact_gelu_also_through_sympy():
    x = jnp.linspace(-3.0, 3.0, 13, dtype=jnp.float64)
    np.testing.assert_array_equal(np.asarray(dvi.gelu_exact(x)),
                                  np.asarray(jax.nn.gelu(x, approximate=False)))
    theta = jnp.asarray(np.random.default_rng(0).normal(size=(12, 1)))
    tau = jnp.asarray(0.3)
    autodiff = dvi.ShallowNetBasis(dvi.gelu_exact, 4).evaluate(theta, tau)
    sympy = dvi.ShallowNetBasis(dvi.gelu_exact, 4, derivatives="sympy").evaluate(theta, tau)
    np.testing.assert_allclose(np.asarray(sympy), np.asarray(autodiff), rtol=1e-14)


# -- the same solver, and its energy on the oscillator ------------------------------------------

# L = v²/2 − q²/2, h = 0.5, 2000 steps (issue 52).
OSCILLATOR = problems.harmonic_oscillator(m=1.0, k=1.0, dtype=jnp.float64).with_span(
    n_steps=2000, dt=0.5
)


@eqx.filter_jit
def _run(solver):
    p = OSCILLATOR
    return diffrax.diffeqsolve(p.term, solver, p.t0, p.t1, p.dt, p.y0, args=p.args,
                               saveat=diffrax.SaveAt(steps=True), max_steps=p.n_steps)


def relative_energy_error(sol) -> float:
    p = OSCILLATOR
    energy = np.asarray(jax.vmap(lambda q, v: p.energy(0.0, q, v))(*sol.ys))
    e0 = float(p.energy(0.0, *p.y0))
    return float(np.max(np.abs(energy - e0)) / abs(e0))


@pytest.mark.parametrize(
    "jax_function, ours",
    [(jnp.tanh, dvi.tanh), (jax.nn.gelu, dvi.gelu), (jax.nn.sigmoid, dvi.sigmoid)],
    ids=["jnp.tanh", "jax.nn.gelu", "jax.nn.sigmoid"],
)
def test_a_jax_activation_gets_the_projected_step_and_its_energy(jax_function, ours):
    with warnings.catch_warnings():
        warnings.simplefilter("error", dvi.AllParameterFallbackWarning)
        solver = dvi.NetworkVI(dvi.ShallowNetBasis(jax_function, 10))
    package = dvi.NetworkVI(dvi.ShallowNetBasis(ours, 10))
    assert solver.formulation == package.formulation == dvi.VariableProjection()
    assert type(solver.root_finder) is type(package.root_finder) is dvi.RoundoffNewton
    assert solver.root_finder == package.root_finder
    assert solver == package  # so the compiled solve is shared too
    sol = _run(solver)
    assert sol.result == diffrax.RESULTS.successful
    assert int(np.sum(np.isfinite(np.asarray(sol.ts)))) == OSCILLATOR.n_steps
    assert relative_energy_error(sol) <= 1e-12


def test_gelu_exact_gets_the_projected_step():
    for activation in (dvi.gelu_exact, functools.partial(jax.nn.gelu, approximate=False)):
        solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, 10))
        assert solver.formulation == dvi.VariableProjection()
        assert type(solver.root_finder) is dvi.RoundoffNewton


# -- the fallback warning -----------------------------------------------------------------------


def _fallback_warnings(record):
    return [w for w in record if issubclass(w.category, dvi.AllParameterFallbackWarning)]


def test_an_activation_without_a_rule_warns_once_naming_the_fallback():
    with pytest.warns(dvi.AllParameterFallbackWarning) as record:
        for _ in range(3):  # the same lambda, rebuilt: one warning
            solver = dvi.NetworkVI(dvi.ShallowNetBasis(lambda x: jnp.tanh(x) ** 3, 10))
    assert type(solver.formulation) is dvi.FreeEndpoints
    assert type(solver.root_finder) is dvi.LevenbergMarquardt
    fallback = _fallback_warnings(record)
    assert len(fallback) == 1
    message = str(fallback[0].message)
    for words in ("FreeEndpoints()", "LevenbergMarquardt()", "not isolated", "energy drifts",
                  "formulation=", "<lambda>"):
        assert words in message
    assert fallback[0].filename == __file__  # it points at the user's line


def test_an_explicit_step_does_not_warn():
    def own(x):
        return jnp.tanh(x) ** 3

    chosen = [
        dict(formulation=dvi.FreeEndpoints()),
        dict(formulation=dvi.InterpolatingEndpoints()),
        dict(root_finder=dvi.LevenbergMarquardt()),
        dict(seed=dvi.SeedPolicy(reuse_neurons=True)),
        dict(seed=dvi.SeedPolicy(dvi.PreviousStep())),
    ]
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        for options in chosen:
            assert type(dvi.NetworkVI(dvi.ShallowNetBasis(own, 10), **options).formulation) in (
                dvi.FreeEndpoints, dvi.InterpolatingEndpoints)
        # nor do the activations of the projected step, nor networks the projection cannot
        # take whatever their activation (mirrored pairs, two hidden layers)
        dvi.NetworkVI(dvi.ShallowNetBasis(dvi.relu_k(3), 10))
        dvi.NetworkVI(dvi.ShallowNetBasis(own, 10, symmetry=dvi.MirrorPairs()))
        dvi.NetworkVI(dvi.DenseNetBasis(own, 4, 4),
                      seed=dvi.SeedPolicy(initial_guess=dvi.LSGD()))
    assert _fallback_warnings(record) == []
    # the same activation left to the default warns: the options above are what silenced it
    with pytest.warns(dvi.AllParameterFallbackWarning, match="formulation="):
        dvi.NetworkVI(dvi.ShallowNetBasis(own, 10))
