"""`LagrangianTerm` and `IODETerm`: maps, Legendre inverse, validation, standard solvers."""

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi._terms import (  # noqa: E402
    AbstractMechanicalTerm,
    IODETerm,
    LagrangianTerm,
    unwrap_term,
)


# A two-degree-of-freedom Lagrangian with a position-dependent mass matrix, a magnetic
# (linear-in-v) term and a potential: L = ½ vᵀM(q)v + A(q)·v − V(q).
def mass_matrix(q):
    return jnp.array(
        [
            [2.0 + jnp.sin(q[0]) ** 2, 0.3 * jnp.cos(q[1])],
            [0.3 * jnp.cos(q[1]), 1.0 + q[0] ** 2],
        ]
    )


def vector_potential(q):
    return jnp.stack([0.5 * q[1], -0.2 * q[0]])


def potential(q):
    return 0.5 * q[0] ** 2 + jnp.cos(q[1])


def lagrangian(t, q, v, args):
    return 0.5 * v @ mass_matrix(q) @ v + vector_potential(q) @ v - potential(q)


def hand_momentum(q, v):
    return mass_matrix(q) @ v + vector_potential(q)


def hand_force(q, v):
    f0 = jnp.sin(q[0]) * jnp.cos(q[0]) * v[0] ** 2 + q[0] * v[1] ** 2 - 0.2 * v[1] - q[0]
    f1 = -0.3 * jnp.sin(q[1]) * v[0] * v[1] + 0.5 * v[0] + jnp.sin(q[1])
    return jnp.stack([f0, f1])


def hand_velocity(q, p):
    return jnp.linalg.solve(mass_matrix(q), p - vector_potential(q))


def hand_energy(q, p):
    v = hand_velocity(q, p)
    return 0.5 * v @ mass_matrix(q) @ v + potential(q)


def _tsit5(term, y0, t1=1.0, args=None):
    return diffrax.diffeqsolve(
        term,
        diffrax.Tsit5(),
        t0=0.0,
        t1=t1,
        dt0=0.1,
        y0=y0,
        args=args,
        saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, t1, 5, dtype=jnp.result_type(y0[0]))),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
    ).ys


# -- LagrangianTerm maps ---------------------------------------------------------------------
def test_momentum_force_energy_match_hand_derivatives():
    term = LagrangianTerm(lagrangian)
    rng = np.random.default_rng(0)
    qs, vs, ps = (jnp.asarray(rng.normal(size=(6, 2))) for _ in range(3))

    @jax.jit
    @jax.vmap
    def evaluate(q, v, p):
        return (
            term.momentum_and_force(0.0, q, v, None),
            (term.momentum(0.0, q, v, None), term.force(0.0, q, v, None)),
            term.energy(0.0, q, p, None),
            term.vf(0.0, (q, p), None),
            (hand_momentum(q, v), hand_force(q, v), hand_energy(q, p)),
            (hand_velocity(q, p), hand_force(q, hand_velocity(q, p))),
        )

    (mom, force), (mom2, force2), energy, (dq, dp), hand, hand_vf = evaluate(qs, vs, ps)
    np.testing.assert_allclose(mom, hand[0], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(force, hand[1], rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(mom2, mom)
    np.testing.assert_array_equal(force2, force)
    np.testing.assert_allclose(energy, hand[2], rtol=1e-13)
    # Hamilton's equations as the vector field
    np.testing.assert_allclose(dq, hand_vf[0], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(dp, hand_vf[1], rtol=1e-13, atol=1e-15)


def test_legendre_inverse_exact_after_one_iteration_for_quadratic_lagrangian():
    term = LagrangianTerm(lagrangian)  # legendre_iterations=1
    assert term.legendre_iterations == 1
    rng = np.random.default_rng(1)
    qs, ps = (jnp.asarray(rng.normal(size=(5, 2))) for _ in range(2))
    got = jax.jit(jax.vmap(lambda q, p: term.velocity(0.0, q, p, None)))(qs, ps)
    np.testing.assert_allclose(got, jax.vmap(hand_velocity)(qs, ps), rtol=1e-13, atol=1e-15)


def _cosh_lagrangian(t, q, v, args):
    return jnp.sum(jnp.cosh(v) - 0.5 * q**2)


def test_legendre_inverse_converges_for_non_quadratic_lagrangian():
    q = jnp.array([0.3, -0.4])
    p = jnp.array([0.9, -2.5])
    exact = jnp.arcsinh(p)  # p = sinh(v)
    errors = []
    for n in range(1, 9):
        v = LagrangianTerm(_cosh_lagrangian, legendre_iterations=n).velocity(0.0, q, p, None)
        errors.append(float(jnp.max(jnp.abs(v - exact))))
    assert errors[0] > 1e-2  # one Newton step is not enough
    assert all(b < a for a, b in zip(errors[:5], errors[1:6], strict=True))
    assert errors[-1] < 1e-14
    converged = LagrangianTerm(_cosh_lagrangian, legendre_iterations=8)
    energy = converged.energy(0.0, q, p, None)
    want = jnp.sum(p * exact - jnp.cosh(exact) + 0.5 * q**2)
    np.testing.assert_allclose(energy, want, rtol=1e-14)


def test_closed_form_velocity_is_used():
    calls = []

    def velocity(t, q, p, args):
        calls.append(None)
        return 2.0 * p  # deliberately not the inverse of ∂L/∂v, to see that it is used

    term = LagrangianTerm(_cosh_lagrangian, velocity)
    q, p = jnp.array([0.1, 0.2]), jnp.array([0.3, -0.4])
    np.testing.assert_allclose(term.velocity(0.0, q, p, None), 2.0 * p)
    dq, _ = term.vf(0.0, (q, p), None)
    np.testing.assert_allclose(dq, 2.0 * p)
    assert len(calls) == 2

    # A degenerate Lagrangian (linear in v) has no Newton inverse but works with a closed form.
    def degenerate(t, q, v, args):
        return q[1] * v[0] - 0.5 * q[1] ** 2 - jnp.cos(q[0])

    def vbar(t, q, p, args):
        return jnp.stack([q[1], jnp.sin(q[0])])

    # Without one, the Newton inverse meets a singular ∂²L/∂v² and refuses (no NaN velocity).
    with pytest.raises(RuntimeError, match="degenerate Lagrangian"):
        LagrangianTerm(degenerate).velocity(0.0, q, p, None)
    closed = LagrangianTerm(degenerate, vbar).velocity(0.0, q, p, None)
    np.testing.assert_allclose(closed, [0.2, np.sin(0.1)], rtol=1e-15)


class _ParametricLagrangian(eqx.Module):
    stiffness: jax.Array

    def __call__(self, t, q, v, args):
        return jnp.sum(0.5 * v**2 - 0.5 * self.stiffness * q**2)


def test_module_lagrangian_parameters_are_differentiable():
    term = LagrangianTerm(_ParametricLagrangian(jnp.asarray(3.0)))
    q, v = jnp.array([0.5, -1.0]), jnp.array([0.2, 0.1])
    np.testing.assert_allclose(term.force(0.0, q, v, None), -3.0 * q)
    grads = jax.grad(lambda tm: jnp.sum(tm.force(0.0, q, v, None)))(term)
    np.testing.assert_allclose(grads.lagrangian.stiffness, -jnp.sum(q))


def test_lagrangian_term_keeps_low_precision():
    term = LagrangianTerm(lagrangian)  # numerical Legendre inverse
    evaluate = jax.jit(lambda q, p: (term.vf(0.0, (q, p), None), term.energy(0.0, q, p, None)))
    for dtype in (jnp.float16, jnp.float32):
        q, p = jnp.array([0.2, -0.1], dtype), jnp.array([0.3, 0.4], dtype)
        (dq, dp), energy = evaluate(q, p)
        assert dq.dtype == dp.dtype == energy.dtype == dtype
        np.testing.assert_allclose(dq, hand_velocity(q.astype(float), p.astype(float)), rtol=1e-2)
    ys = _tsit5(term, (jnp.array([0.2, -0.1], jnp.float32),) * 2)
    assert ys[0].dtype == ys[1].dtype == jnp.float32


# -- validation ------------------------------------------------------------------------------
def test_non_scalar_lagrangian_rejected():
    term = LagrangianTerm(lambda t, q, v, args: 0.5 * v**2)
    q = jnp.array([0.1, 0.2])
    with pytest.raises(ValueError, match="scalar"):
        term.momentum(0.0, q, q, None)
    with pytest.raises(ValueError, match="scalar"):
        term(0.0, q, q, None)


def test_dtype_promoting_lagrangian_rejected():
    constant = jnp.asarray(0.5, dtype=jnp.float64)
    term = LagrangianTerm(lambda t, q, v, args: jnp.sum(constant * v**2))
    q = jnp.array([0.1, 0.2], dtype=jnp.float32)
    with pytest.raises(ValueError, match="dtype"):
        term.force(0.0, q, q, None)
    with pytest.raises(ValueError, match="dtype"):
        _tsit5(term, (q, q))
    # the same Lagrangian is fine in float64
    term.force(0.0, q.astype(jnp.float64), q.astype(jnp.float64), None)


def test_constructor_validation():
    with pytest.raises(TypeError, match="lagrangian"):
        LagrangianTerm(1.0)
    with pytest.raises(TypeError, match="velocity"):
        LagrangianTerm(lagrangian, velocity=3)
    with pytest.raises(ValueError, match="legendre_iterations"):
        LagrangianTerm(lagrangian, legendre_iterations=0)
    with pytest.raises(TypeError, match="force"):
        IODETerm(lambda t, q, v, a: v, None)
    with pytest.raises(TypeError, match="hamiltonian"):
        IODETerm(lambda t, q, v, a: v, lambda t, q, v, a: q, hamiltonian="H")


def test_state_must_be_a_pair():
    term = LagrangianTerm(lagrangian)
    with pytest.raises(ValueError, match=r"y0 = \(q, p\) must be a pair"):
        term.vf(0.0, jnp.zeros(4), None)


# -- IODETerm ----------------------------------------------------------------------------------
def _oscillator_iode(velocity=True, hamiltonian=True):
    """L = v² − 3q²/2 written as momentum and force maps."""
    return IODETerm(
        lambda t, q, v, args: 2.0 * v,
        lambda t, q, v, args: -3.0 * q,
        velocity=(lambda t, q, p, args: p / 2.0) if velocity else None,
        hamiltonian=(lambda t, q, p, a: jnp.sum(p**2 / 4.0 + 1.5 * q**2)) if hamiltonian else None,
    )


def test_iode_term_maps_and_solve():
    term = _oscillator_iode()
    q, v = jnp.array([0.5]), jnp.array([0.25])
    p, f = term.momentum_and_force(0.0, q, v, None)
    np.testing.assert_allclose(p, [0.5])
    np.testing.assert_allclose(f, [-1.5])
    np.testing.assert_allclose(term.energy(0.0, q, p, None), 0.0625 + 0.375)
    ys = _tsit5(term, (jnp.array([0.5]), jnp.array([0.0])))
    omega = np.sqrt(1.5)
    ts = np.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(ys[0][:, 0], 0.5 * np.cos(omega * ts), rtol=1e-8)


def test_iode_term_without_velocity_cannot_use_standard_solver():
    term = _oscillator_iode(velocity=False)
    with pytest.raises(RuntimeError, match="velocity map"):
        term.velocity(0.0, jnp.zeros(1), jnp.zeros(1), None)
    with pytest.raises(RuntimeError, match="velocity map"):
        _tsit5(term, (jnp.array([0.5]), jnp.array([0.0])))
    # its momentum and force remain available for the variational solvers
    np.testing.assert_allclose(term.momentum(0.0, jnp.ones(1), jnp.ones(1), None), [2.0])


def test_iode_term_without_velocity_is_integrated_by_network_vi():
    # diffeqsolve traces the vector field for its shapes before the first step; a term with
    # no velocity map must pass that check, since NetworkVI never evaluates the map.
    term = _oscillator_iode(velocity=False)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))
    ts = jnp.linspace(0.0, 1.0, 11)
    sol = diffrax.diffeqsolve(
        term, solver, 0.0, 1.0, 0.1, (jnp.array([0.5]), jnp.array([0.0])),
        saveat=diffrax.SaveAt(ts=ts),
    )
    assert sol.result == diffrax.RESULTS.successful
    exact = 0.5 * np.cos(np.sqrt(1.5) * np.asarray(ts))
    np.testing.assert_allclose(sol.ys[0][:, 0], exact, atol=1e-10)


def test_iode_term_without_hamiltonian_has_no_energy():
    term = _oscillator_iode(hamiltonian=False)
    with pytest.raises(ValueError, match="hamiltonian"):
        term.energy(0.0, jnp.zeros(1), jnp.zeros(1), None)


def test_iode_term_checks_shape_and_dtype():
    wrong_shape = IODETerm(lambda t, q, v, a: jnp.concatenate([v, v]), lambda t, q, v, a: q)
    with pytest.raises(ValueError, match="momentum map returned shape"):
        wrong_shape.momentum(0.0, jnp.zeros(2), jnp.zeros(2), None)
    promoting = IODETerm(
        lambda t, q, v, a: v, lambda t, q, v, a: q * jnp.asarray(1.0, dtype=jnp.float64)
    )
    q32 = jnp.zeros(2, jnp.float32)
    with pytest.raises(ValueError, match="force map returned dtype"):
        promoting.force(0.0, q32, q32, None)


# -- plain-ODE view and unwrapping ---------------------------------------------------------------
@pytest.mark.parametrize("kind", ["lagrangian", "iode"])
def test_to_ode_gives_same_solution(kind):
    if kind == "lagrangian":
        term, y0 = LagrangianTerm(lagrangian), (jnp.array([0.2, -0.1]), jnp.array([0.3, 0.4]))
    else:
        term, y0 = _oscillator_iode(), (jnp.array([0.5]), jnp.array([0.1]))
    ode = term.to_ode()
    assert isinstance(ode, diffrax.ODETerm)
    direct, via_ode = _tsit5(term, y0), _tsit5(ode, y0)
    for a, b in zip(direct, via_ode, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-15)


def test_unwrap_term():
    term = LagrangianTerm(lagrangian)
    assert unwrap_term(term) == (term, 1)
    assert isinstance(term, AbstractMechanicalTerm)

    class Wrapped:  # the shape of diffrax's internal WrapTerm
        def __init__(self, term, direction):
            self.term, self.direction = term, direction

    inner, direction = unwrap_term(Wrapped(Wrapped(term, -1), -1))
    assert inner is term and direction == 1
    inner, direction = unwrap_term(Wrapped(term, -1))
    assert inner is term and direction == -1
    with pytest.raises(TypeError, match="LagrangianTerm or IODETerm"):
        unwrap_term(diffrax.ODETerm(lambda t, y, args: y))
