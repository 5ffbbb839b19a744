"""`sympy_lagrangian_term` and the separable term pair for `diffrax.SemiImplicitEuler`."""

import subprocess
import sys

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy

import diffrax_vi as dvi
from diffrax_vi.symbolic.terms import SympyLagrangianTerm, sympy_lagrangian_term
from tests.helpers import henon_heiles_lagrangian as _henon_heiles

jax.config.update("jax_enable_x64", True)

t_, q1, q2, v1, v2 = sympy.symbols("t q1 q2 v1 v2", real=True)
l1, l2, m1, m2, g, lam = sympy.symbols("l1 l2 m1 m2 g lam", positive=True)


# -- the same systems in sympy and in jnp ----------------------------------------------------
def _pendulum_sympy():
    lagrangian = m1 * l1**2 * v1**2 / 2 + m1 * g * l1 * sympy.cos(q1)
    return dvi.sympy_lagrangian_term(lagrangian, [q1], [v1], params=[l1, m1, g])


def _pendulum_jnp(t, q, v, args):
    length, m, gr = args["l1"], args["m1"], args["g"]
    return m * length**2 * v[0] ** 2 / 2 + m * gr * length * jnp.cos(q[0])


def _double_pendulum_sympy():
    kinetic = (
        (m1 + m2) * l1**2 * v1**2 / 2
        + m2 * l2**2 * v2**2 / 2
        + m2 * l1 * l2 * v1 * v2 * sympy.cos(q1 - q2)
    )
    potential = -(m1 + m2) * g * l1 * sympy.cos(q1) - m2 * g * l2 * sympy.cos(q2)
    return dvi.sympy_lagrangian_term(
        kinetic - potential, "q1 q2", "v1 v2", params="l1 l2 m1 m2 g"
    )


def _double_pendulum_jnp(t, q, v, args):
    a, b, ma, mb, gr = (args[k] for k in ("l1", "l2", "m1", "m2", "g"))
    kinetic = (
        0.5 * (ma + mb) * a**2 * v[0] ** 2
        + 0.5 * mb * b**2 * v[1] ** 2
        + mb * a * b * v[0] * v[1] * jnp.cos(q[0] - q[1])
    )
    return kinetic + (ma + mb) * gr * a * jnp.cos(q[0]) + mb * gr * b * jnp.cos(q[1])


def _henon_heiles_sympy():
    potential = (q1**2 + q2**2) / 2 + lam * (q1**2 * q2 - q2**3 / 3)
    return dvi.sympy_lagrangian_term(
        (v1**2 + v2**2) / 2 - potential, [q1, q2], [v1, v2], params=[lam]
    )


def _henon_heiles_jnp(t, q, v, args):
    potential = 0.5 * jnp.sum(q**2) + args["lam"] * (q[0] ** 2 * q[1] - q[1] ** 3 / 3)
    return 0.5 * jnp.sum(v**2) - potential


SYSTEMS = {
    "pendulum": (_pendulum_sympy, _pendulum_jnp, 1, {"l1": 1.5, "m1": 0.7, "g": 9.81}),
    "double_pendulum": (
        _double_pendulum_sympy,
        _double_pendulum_jnp,
        2,
        {"l1": 2.0, "l2": 3.0, "m1": 1.0, "m2": 2.0, "g": 9.80665},
    ),
    "henon_heiles": (_henon_heiles_sympy, _henon_heiles_jnp, 2, {"lam": 1.0}),
}


def _close(a, b, rtol=1e-14, atol=1e-14):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol)


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_sympy_term_matches_jnp_term(name):
    make, fn, dim, args = SYSTEMS[name]
    sym, ref = make(), dvi.LagrangianTerm(fn)
    assert isinstance(sym, dvi.LagrangianTerm) and isinstance(sym, SympyLagrangianTerm)
    assert sym.legendre_iterations == 1  # quadratic in v: one exact Newton step
    rng = np.random.default_rng(0)
    qs, vs, ps = (jnp.asarray(rng.normal(size=(8, dim))) for _ in range(3))

    def maps(term):
        @jax.jit
        @jax.vmap
        def evaluate(q, v, p):
            return (
                term(0.3, q, v, args),
                term.momentum_and_force(0.3, q, v, args),
                term.velocity(0.3, q, p, args),
                term.energy(0.3, q, p, args),
                term.vf(0.3, (q, p), args),
            )

        return evaluate(qs, vs, ps)

    got, want = maps(sym), maps(ref)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        assert a.dtype == b.dtype == jnp.float64 and a.shape == b.shape
        _close(a, b)
    # the velocity really inverts the momentum
    p_back = jax.vmap(lambda q, p: sym.momentum(0.3, q, sym.velocity(0.3, q, p, args), args))
    _close(p_back(qs, ps), ps, rtol=1e-13)


def test_params_as_tuple_names_and_vmap():
    term = _pendulum_sympy()
    q, v = jnp.array([0.4]), jnp.array([-0.3])
    as_dict = term.momentum_and_force(0.0, q, v, {"l1": 1.5, "m1": 0.7, "g": 9.81, "x": "ok"})
    as_tuple = term.momentum_and_force(0.0, q, v, (1.5, 0.7, 9.81))
    for a, b in zip(as_dict, as_tuple, strict=True):
        np.testing.assert_array_equal(a, b)

    # vmap over a parameter (the pendulum length) inside args
    lengths = jnp.linspace(0.5, 2.0, 7)
    force = jax.jit(
        jax.vmap(lambda length: term.force(0.0, q, v, {"l1": length, "m1": 0.7, "g": 9.81}))
    )(lengths)
    ref = dvi.LagrangianTerm(_pendulum_jnp)
    want = jax.vmap(lambda length: ref.force(0.0, q, v, {"l1": length, "m1": 0.7, "g": 9.81}))(
        lengths
    )
    _close(force, want)
    _close(force[:, 0], -0.7 * 9.81 * lengths * jnp.sin(0.4))
    # and over the args of a whole Tsit5 solve
    y0 = (jnp.array([0.5]), jnp.array([0.0]))
    solve = jax.vmap(
        lambda length: diffrax.diffeqsolve(
            term, diffrax.Tsit5(), 0.0, 0.5, 0.05, y0, args=(length, 1.0, 1.0)
        ).ys[0][-1, 0]
    )
    ends = solve(jnp.array([1.0, 4.0]))
    assert ends[0] < ends[1] < 0.5  # the longer pendulum swings more slowly


def test_time_dependent_lagrangian():
    # a parametrically driven oscillator L = v²/2 − (1 + ε sin ωt) q²/2
    eps, omega = sympy.symbols("eps omega")
    lagrangian = v1**2 / 2 - (1 + eps * sympy.sin(omega * t_)) * q1**2 / 2
    sym = dvi.sympy_lagrangian_term(lagrangian, [q1], [v1], t="t", params=[eps, omega])
    assert sym.time == t_

    def fn(t, q, v, args):
        e, w = args
        return jnp.sum(v**2 / 2 - (1 + e * jnp.sin(w * t)) * q**2 / 2)

    ref, args = dvi.LagrangianTerm(fn), (0.3, 2.0)
    q, v = jnp.array([0.7]), jnp.array([0.2])
    for t in (0.0, 0.4, 1.3):
        for a, b in zip(
            sym.momentum_and_force(t, q, v, args),
            ref.momentum_and_force(t, q, v, args),
            strict=True,
        ):
            _close(a, b)
        _close(sym.energy(t, q, v, args), ref.energy(t, q, v, args))


def _tsit5(term, y0, args, t1=1.0):
    return diffrax.diffeqsolve(
        term,
        diffrax.Tsit5(),
        0.0,
        t1,
        0.05,
        y0,
        args=args,
        saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, t1, 5)),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
    ).ys


def test_tsit5_matches_jnp_term():
    _, fn, _, args = SYSTEMS["double_pendulum"]
    y0 = (jnp.array([np.pi / 4, np.pi / 2]), jnp.array([3.3321622036187746, 7.0685834705770345]))
    got = _tsit5(_double_pendulum_sympy(), y0, args)
    want = _tsit5(dvi.LagrangianTerm(fn), y0, args)
    for a, b in zip(got, want, strict=True):
        _close(a, b, rtol=1e-10, atol=1e-11)


def test_network_vi_on_sympy_harmonic_oscillator():
    q, v, m, k = sympy.symbols("q v m k", real=True)
    term = dvi.sympy_lagrangian_term(m * v**2 / 2 - k * q**2 / 2, q, v, params=(m, k))
    mass, stiffness = 2.0, 3.0
    q0, p0 = jnp.array([1.0]), jnp.array([0.5])
    ts = jnp.linspace(0.0, 1.0, 11)
    sol = diffrax.diffeqsolve(
        term,
        dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8)),
        0.0,
        1.0,
        0.1,
        (q0, p0),
        args={"m": mass, "k": stiffness},
        saveat=diffrax.SaveAt(ts=ts),
    )
    omega = np.sqrt(stiffness / mass)
    exact_q = q0[0] * np.cos(omega * ts) + p0[0] / (mass * omega) * np.sin(omega * ts)
    exact_p = -mass * omega * q0[0] * np.sin(omega * ts) + p0[0] * np.cos(omega * ts)
    _close(sol.ys[0][:, 0], exact_q, rtol=0, atol=1e-10)
    _close(sol.ys[1][:, 0], exact_p, rtol=0, atol=1e-10)


# -- precision and static-friendliness --------------------------------------------------------
def test_float32_stays_float32():
    term = _double_pendulum_sympy()
    args = {k: jnp.float32(x) for k, x in SYSTEMS["double_pendulum"][3].items()}
    q = jnp.array([0.2, -0.1], jnp.float32)
    jaxpr = jax.make_jaxpr(lambda q, v, a: term.momentum_and_force(0.0, q, v, a))(q, q, args)
    assert "f64" not in str(jaxpr)
    jaxpr = jax.make_jaxpr(lambda q, p, a: (term.vf(0.0, (q, p), a), term.energy(0.0, q, p, a)))(
        q, q, args
    )
    assert "f64" not in str(jaxpr)
    # float64 parameter values are cast to the working precision
    (dq, dp), energy = jax.jit(
        lambda q, p: (
            term.vf(0.0, (q, p), (2.0, 3.0, 1.0, 2.0, 9.8)),
            term.energy(0.0, q, p, (2.0, 3.0, 1.0, 2.0, 9.8)),
        )
    )(q, q)
    assert dq.dtype == dp.dtype == energy.dtype == jnp.float32


def test_terms_are_static_friendly():
    a, b = _henon_heiles_sympy(), _henon_heiles_sympy()
    assert a == b and hash(a) == hash(b)
    assert not jax.tree.leaves(a)  # nothing but static structure
    traces = []

    @eqx.filter_jit
    def force(term, q):
        traces.append(None)
        return term.force(0.0, q, q, {"lam": 1.0})

    force(a, jnp.ones(2))
    force(b, jnp.ones(2))
    assert len(traces) == 1
    assert a != _double_pendulum_sympy()


def test_import_does_not_import_sympy():
    code = "import sys, diffrax_vi; assert 'sympy' not in sys.modules, 'sympy imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


# -- validation -----------------------------------------------------------------------------
def test_unknown_symbols_refused():
    k = sympy.Symbol("k")
    with pytest.raises(ValueError, match=r"symbol\(s\) k, which are neither"):
        sympy_lagrangian_term(v1**2 / 2 - k * q1**2 / 2, [q1], [v1])
    with pytest.raises(ValueError, match=r"symbol\(s\) t, which"):  # time not declared
        sympy_lagrangian_term(v1**2 / 2 - t_ * q1**2, [q1], [v1], params=[k])
    with pytest.raises(ValueError, match="symbol.*q2"):
        sympy_lagrangian_term(v1**2 / 2 - q1 * q2, [q1], [v1])


def test_declaration_errors():
    lagrangian = (v1**2 + v2**2) / 2 - q1**2 * q2
    with pytest.raises(ValueError, match="same length"):
        sympy_lagrangian_term(lagrangian, [q1, q2], [v1])
    with pytest.raises(ValueError, match="q1 is declared twice"):
        sympy_lagrangian_term(lagrangian, [q1, q1], [v1, v2])
    with pytest.raises(ValueError, match="v1 is declared twice.*velocity.*parameter"):
        sympy_lagrangian_term(lagrangian, [q1, q2], [v1, v2], params=[v1])
    with pytest.raises(ValueError, match="at least one"):
        sympy_lagrangian_term(lagrangian, [], [])
    with pytest.raises(TypeError, match="scalar"):
        sympy_lagrangian_term(sympy.Matrix([v1, v2]), [q1, q2], [v1, v2])
    with pytest.raises(TypeError, match="Symbols or names"):
        sympy_lagrangian_term(lagrangian, [q1, 2.0], [v1, v2])
    with pytest.raises(ValueError, match="legendre_iterations"):
        sympy_lagrangian_term(lagrangian, [q1, q2], [v1, v2], legendre_iterations=0)


def test_call_time_errors():
    term = _pendulum_sympy()
    q = jnp.array([0.1])
    with pytest.raises(ValueError, match="'g' are missing from args"):
        term.force(0.0, q, q, {"l1": 1.0, "m1": 1.0})
    with pytest.raises(ValueError, match="sequence of length 2"):
        term.force(0.0, q, q, (1.0, 1.0))
    with pytest.raises(TypeError, match="pass their values as args"):
        term.force(0.0, q, q, None)
    with pytest.raises(ValueError, match="must be a scalar"):
        term.force(0.0, q, q, (jnp.ones(3), 1.0, 1.0))
    with pytest.raises(ValueError, match=r"must have shape \(1,\)"):
        term.force(0.0, jnp.zeros(2), jnp.zeros(2), (1.0, 1.0, 1.0))
    # the same errors at trace time
    with pytest.raises(ValueError, match="missing"):
        jax.jit(lambda q: term.force(0.0, q, q, {"l1": 1.0}))(q)


def test_non_quadratic_and_degenerate_lagrangians():
    q, v = jnp.array([0.3, -0.4]), jnp.array([0.1, 0.2])
    p = jnp.array([0.9, -2.5])
    lagrangian = sympy.cosh(v1) + sympy.cosh(v2) - (q1**2 + q2**2) / 2
    term = sympy_lagrangian_term(lagrangian, [q1, q2], [v1, v2])
    assert term.legendre_iterations is None
    _close(term.momentum(0.0, q, v, None), jnp.sinh(v))  # enough for the variational solvers
    with pytest.raises(ValueError, match="legendre_iterations"):
        term.velocity(0.0, q, p, None)
    converged = sympy_lagrangian_term(lagrangian, [q1, q2], [v1, v2], legendre_iterations=8)
    _close(converged.velocity(0.0, q, p, None), jnp.arcsinh(p))
    ref = dvi.LagrangianTerm(
        lambda t, q, v, a: jnp.sum(jnp.cosh(v) - q**2 / 2), legendre_iterations=8
    )
    _close(converged.energy(0.0, q, p, None), ref.energy(0.0, q, p, None))

    degenerate = sympy_lagrangian_term(q2 * v1 - q2**2 / 2 - sympy.cos(q1), "q1 q2", "v1 v2")
    _close(degenerate.momentum(0.0, q, v, None), [q[1], 0.0])
    with pytest.raises(ValueError, match="degenerate"):
        degenerate.vf(0.0, (q, p), None)
    closed = sympy_lagrangian_term(
        q2 * v1 - q2**2 / 2 - sympy.cos(q1),
        "q1 q2",
        "v1 v2",
        velocity=lambda t, q, p, a: jnp.stack([q[1], jnp.sin(q[0])]),
    )
    _close(closed.velocity(0.0, q, p, None), [q[1], jnp.sin(q[0])])


# -- separable pairs for SemiImplicitEuler -----------------------------------------------------
def _oscillator(t, q, v, args):
    return jnp.sum(2.0 * v**2 / 2 - 3.0 * q**2 / 2)  # m = 2, k = 3


def _henon_heiles_energy(q, p):
    return 0.5 * jnp.sum(p**2 + q**2, -1) + q[..., 0] ** 2 * q[..., 1] - q[..., 1] ** 3 / 3


def _semi_implicit(pair, y0, t1, dt, args=None, n_save=2):
    return diffrax.diffeqsolve(
        pair,
        diffrax.SemiImplicitEuler(),
        0.0,
        t1,
        dt,
        y0,
        args=args,
        saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, t1, n_save)),
        max_steps=None,
    ).ys


def test_semi_implicit_euler_harmonic_oscillator():
    term = dvi.LagrangianTerm(_oscillator)
    y0 = (jnp.array([1.0]), jnp.array([0.5]))
    pair = term.separable_terms(y0)
    assert all(isinstance(x, diffrax.ODETerm) for x in pair)
    _close(pair[0].vf(0.0, jnp.array([0.5]), None), [0.25])  # M⁻¹ p
    _close(pair[1].vf(0.0, jnp.array([1.0]), None), [-3.0])  # −∇V
    omega = np.sqrt(1.5)
    exact = 1.0 * np.cos(omega) + 0.5 / (2.0 * omega) * np.sin(omega)
    errors = []
    for dt in (0.02, 0.01, 0.005):
        ys = _semi_implicit(pair, y0, 1.0, dt)
        errors.append(abs(float(ys[0][-1, 0]) - exact))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(rates, 1.0, atol=0.1)
    # bounded energy over many periods (no drift): H = p²/4 + 3q²/2
    q, p = _semi_implicit(pair, y0, 200.0, 0.05, n_save=2001)
    energy = p[:, 0] ** 2 / 4 + 1.5 * q[:, 0] ** 2
    h0 = 0.5**2 / 4 + 1.5
    deviation = jnp.abs(energy - h0)
    assert float(jnp.max(deviation)) < 0.05 * h0
    # the oscillation of the energy does not grow (about 40 periods)
    assert float(jnp.max(deviation[-500:])) < 1.05 * float(jnp.max(deviation[:500]))


def test_semi_implicit_euler_henon_heiles():
    term = dvi.LagrangianTerm(_henon_heiles)
    y0 = (jnp.array([0.1, 0.1]), jnp.array([0.1, 0.1]))
    pair = term.separable_terms(y0)
    reference = _tsit5(term, y0, None, t1=2.0)
    errors = []
    for dt in (0.02, 0.01, 0.005):
        ys = _semi_implicit(pair, y0, 2.0, dt, n_save=5)
        errors.append(float(jnp.max(jnp.abs(ys[0] - reference[0]))))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(rates, 1.0, atol=0.1)
    q, p = _semi_implicit(pair, y0, 500.0, 0.05, n_save=1001)
    energy = _henon_heiles_energy(q, p)
    h0 = float(_henon_heiles_energy(*y0))
    deviation = jnp.abs(energy - h0)
    assert float(jnp.max(deviation)) < 0.1 * h0  # first-order oscillation, 5.5% at dt = 0.05
    assert float(jnp.max(deviation[-250:])) < 1.1 * float(jnp.max(deviation[:250]))
    # the sympy term gives the same pair, its separability checked symbolically
    sym = _henon_heiles_sympy().separable_terms()
    ys = _semi_implicit(sym, y0, 2.0, 0.01, args={"lam": 1.0}, n_save=5)
    ref = _semi_implicit(pair, y0, 2.0, 0.01, n_save=5)
    for a, b in zip(ys, ref, strict=True):
        _close(a, b, rtol=1e-13)


def test_non_separable_lagrangians_refused():
    _, fn, _, args = SYSTEMS["double_pendulum"]
    y0 = (jnp.array([0.3, 0.2]), jnp.array([0.0, 0.0]))  # p = 0 would hide M'(q)·v
    with pytest.raises(ValueError, match="not separable"):
        dvi.LagrangianTerm(fn).separable_terms(y0, args)
    with pytest.raises(ValueError, match=r"not separable.*∂²L/∂q1∂v1"):
        _double_pendulum_sympy().separable_terms()
    # a magnetic (linear-in-v, q-dependent) term also couples q and v
    magnetic = dvi.LagrangianTerm(lambda t, q, v, a: 0.5 * jnp.sum(v**2) + q[0] * v[1])
    with pytest.raises(ValueError, match="not separable"):
        magnetic.separable_terms((jnp.zeros(2), jnp.zeros(2)))
    # traced states cannot be checked: no error at trace time
    jax.jit(lambda q, p: magnetic.separable_terms((q, p))[1].vf(0.0, q, None))(
        jnp.zeros(2), jnp.zeros(2)
    )


@pytest.mark.slow  # the sympy term equals the hand-written one: test_sympy_term_matches_jnp_term
def test_sympy_double_pendulum_trajectory_matches_hand_written():
    _, fn, _, args = SYSTEMS["double_pendulum"]
    y0 = (jnp.array([np.pi / 4, np.pi / 2]), jnp.array([3.3321622036187746, 7.0685834705770345]))
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(16))
    ts = jnp.linspace(0.0, 0.5, 6)

    def run(term, method):
        return diffrax.diffeqsolve(
            term, method, 0.0, 0.5, 0.05, y0, args=args, saveat=diffrax.SaveAt(ts=ts)
        ).ys

    # Dopri8 follows the same arithmetic path: equal to 1e-12. The network's step equations
    # have non-isolated roots, so the two (differently rounded) Newton paths may settle on
    # different parameters of the same curve: measured 2.3e-12 apart in q and 1.4e-11
    # relative in p (|p| up to 17) after 10 steps.
    for method, rtol, atol in ((diffrax.Dopri8(), 0, 1e-12), (solver, 1e-10, 1e-11)):
        got = run(_double_pendulum_sympy(), method)
        want = run(dvi.LagrangianTerm(fn), method)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol)
