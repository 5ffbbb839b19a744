"""A small program evaluated in NumPy when a step is traced (`_numpy_eval`), against the same
program compiled by XLA."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import _kinetic_structure as kinetic
from diffrax_vi import problems
from diffrax_vi._numpy_eval import Unsupported, evaluate_jaxpr

jax.config.update("jax_enable_x64", True)

# The problems of the library whose term is a Lagrangian (the pendulum's is an IODETerm).
LIBRARY = ["harmonic_oscillator", "double_pendulum", "kepler", "henon_heiles",
           "charged_particle", "coupled_oscillators", "fermi_pasta_ulam", "toda_lattice",
           "outer_solar_system", "spherical_pendulum", "rigid_chain", "perturbed_pendulum",
           "modulated_oscillator", "damped_oscillator", "driven_oscillator"]


# Lagrangians whose programs use a primitive that the evaluator does not know.
LEFT_TO_XLA = {"outer_solar_system": "gather"}  # pairs of bodies picked by index arrays


def _in_numpy_and_compiled(fn, *args):
    closed = jax.make_jaxpr(fn)(*args)
    flat = jax.tree_util.tree_leaves(args)
    ours = evaluate_jaxpr(closed, *[np.asarray(a) for a in flat])
    theirs = jax.tree_util.tree_leaves(jax.jit(fn)(*args))
    return ours, theirs


@pytest.mark.parametrize("name", LIBRARY)
def test_the_lagrangians_derivatives_agree_with_the_compiled_ones(name):
    """The kinetic matrix, the momentum offset and the force of each library problem, at a
    random state, agree with XLA's to a few rounding units."""
    problem = getattr(problems, name)()
    term, args = problem.term, problem.args
    rng = np.random.default_rng(1)
    q = jnp.asarray(rng.normal(size=problem.y0[0].shape) * 0.3 + np.asarray(problem.y0[0]))
    v = jnp.asarray(rng.normal(size=q.shape))
    t = jnp.asarray(0.375)

    def blocks(t, q, v):
        lagrangian = lambda t, q, v: term(t, q, v, args)  # noqa: E731
        return (jax.hessian(lagrangian, argnums=2)(t, q, v),
                jax.grad(lagrangian, argnums=2)(t, q, jnp.zeros_like(v)),
                jax.grad(lagrangian, argnums=1)(t, q, v),
                jax.jacfwd(jax.grad(lagrangian, argnums=2), argnums=1)(t, q, v))

    if name in LEFT_TO_XLA:
        with pytest.raises(Unsupported, match=LEFT_TO_XLA[name]):
            _in_numpy_and_compiled(blocks, t, q, v)
        # evaluated_now compiles it instead
        inputs = tuple(np.asarray(a) for a in (t, q, v))
        ours = jax.tree_util.tree_leaves(kinetic.evaluated_now(blocks, name, inputs))
        theirs = jax.tree_util.tree_leaves(jax.jit(blocks)(t, q, v))
    else:
        ours, theirs = _in_numpy_and_compiled(blocks, t, q, v)
    for a, b in zip(ours, theirs, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        scale = max(1.0, float(np.max(np.abs(b))))
        np.testing.assert_allclose(a, np.asarray(b), rtol=0, atol=64 * 2.2e-16 * scale,
                                   err_msg=name)


def test_shape_and_contraction_rules_agree_with_the_compiled_ones():
    """The rules of the primitives a Lagrangian's program is made of, each exercised."""
    x = jnp.asarray(np.random.default_rng(0).normal(size=(3, 4)))
    y = jnp.asarray(np.random.default_rng(1).normal(size=(4, 3)))

    def program(x, y):
        a = jnp.einsum("ij,jk->ik", x, y)                      # dot_general
        b = jnp.einsum("bij,bjk->bik", x[None], y[None])       # with a batch axis
        c = jnp.pad(x, ((1, 2), (0, 1)))                       # pad
        d = jax.lax.pad(x, 0.5, ((-1, 1, 1), (2, -1, 0)))      # interior and negative pads
        e = jnp.concatenate([x, y.T], axis=0)[::2, 1:3]       # concatenate, strided slice
        f = jnp.where(x > 0, jnp.tanh(x), jnp.exp(x) - 1)      # select_n, compare
        g = jnp.sum(x**3, axis=1) + jnp.max(x, axis=0).sum()   # integer_pow, reductions
        h = jnp.split(x, [1, 3], axis=1)                       # split
        i = jnp.arange(5.0) * jnp.sqrt(jnp.abs(x[0, 0]))       # iota, sqrt, abs
        j = jnp.broadcast_to(x[:, None, 1], (3, 2)).T.reshape(6)  # broadcast, transpose
        k = jax.nn.sigmoid(x) / (1 + jnp.cos(x) ** 2) - jnp.sin(x) * jnp.log1p(x**2)
        return a, b, c, d, e, f, g, *h, i, j, k

    try:
        ours, theirs = _in_numpy_and_compiled(program, x, y)
    except Unsupported as error:
        pytest.fail(f"a primitive of this program is not known: {error}")
    for a, b in zip(ours, theirs, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_allclose(a, np.asarray(b), rtol=1e-14, atol=1e-15)


def test_an_unknown_primitive_is_left_to_xla():
    def program(x):
        return jnp.linalg.solve(x, jnp.ones(2))  # an LU factorisation

    x = jnp.asarray([[2.0, 1.0], [1.0, 3.0]])
    with pytest.raises(Unsupported):
        evaluate_jaxpr(jax.make_jaxpr(program)(x), np.asarray(x))
    # evaluated_now compiles such a program instead, and gives its value
    value = kinetic.evaluated_now(program, None, (np.asarray(x),))
    np.testing.assert_allclose(value, [0.4, 0.2], rtol=1e-15)


@pytest.mark.parametrize("name", ["kepler", "double_pendulum"])
def test_a_solve_compiles_no_program_for_its_kinetic_matrix(name):
    """What the step decides from the kinetic matrix when it is traced (its constant value on
    Kepler, its regularity at a random state on the double pendulum) is read in NumPy: no
    program of its own is compiled for it."""
    from jax.monitoring import (
        register_event_duration_secs_listener,
        unregister_event_duration_listener,
    )

    problem = getattr(problems, name)()
    kinetic._PROGRAMS.clear()
    kinetic._STRUCTURES.clear()
    compiled = []

    def count(event, seconds, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(seconds)

    h = float(problem.dt)
    register_event_duration_secs_listener(count)
    try:
        traced = jax.jit(lambda y: diffrax.diffeqsolve(
            problem.term, dvi.CGVI(6), 0.0, 4 * h, h, y, args=problem.args, max_steps=8,
        ).ys).trace(problem.y0)  # fmt: skip
    finally:
        unregister_event_duration_listener(count)
    assert traced is not None
    assert kinetic._PROGRAMS, "the step read nothing of its kinetic matrix when traced"
    assert all(program.compiled is None for program in kinetic._PROGRAMS.values())
    # diffrax's own eager programs aside (a result code and a dtype cast), nothing compiled
    assert len(compiled) <= 2, compiled


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float16])
@pytest.mark.parametrize("name", ["kepler", "double_pendulum"])
def test_a_low_precision_program_stays_in_its_dtype(name, dtype):
    """In float32 and float16 the NumPy values keep the working dtype and agree with XLA's to
    a few rounding units of it (XLA may compute float16 in float32 and round once; NumPy
    rounds each operation)."""
    problem = getattr(problems, name)(dtype=dtype)
    term, args = problem.term, problem.args
    q = problem.y0[0] + jnp.asarray([0.1, -0.2], dtype)
    v = jnp.asarray([0.3, 0.7], dtype)

    def mass(q, v):
        return jax.hessian(lambda v: term(jnp.zeros((), dtype), q, v, args))(v)

    ours, theirs = _in_numpy_and_compiled(mass, q, v)
    assert ours[0].dtype == dtype
    scale = max(1.0, float(np.max(np.abs(np.asarray(theirs[0], np.float64)))))
    np.testing.assert_allclose(np.asarray(ours[0], np.float64),
                               np.asarray(theirs[0], np.float64),
                               rtol=0, atol=16 * float(jnp.finfo(dtype).eps) * scale)
