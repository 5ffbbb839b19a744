"""The implicit-midpoint seed trajectory (`diffrax_vi._seeding.trajectories`)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffrax_vi import problems
from diffrax_vi._quadrature import GaussLegendre
from diffrax_vi._seeding.trajectories import implicit_midpoint, labels_curve
from diffrax_vi._terms import IODETerm, LagrangianTerm

F64 = jnp.float64


# -- 7. implicit midpoint seed ---------------------------------------------------------------


def oscillator(t, q, v, args):
    return jnp.sum(0.5 * v**2 - 0.5 * q**2)


def _midpoint(term, t, h, q0, p0, substeps, iterations=3, dtype=F64):
    return implicit_midpoint(
        term,
        jnp.asarray(t, dtype),
        jnp.asarray(h, dtype),
        jnp.asarray(q0, dtype),
        jnp.asarray(p0, dtype),
        None,
        substeps,
        iterations,
    )


def test_implicit_midpoint_second_order_on_oscillator():
    term = LagrangianTerm(oscillator)
    q0, p0, h = 0.5, 0.3, 1.0
    q_exact = q0 * math.cos(h) + p0 * math.sin(h)
    p_exact = p0 * math.cos(h) - q0 * math.sin(h)
    errors_q, errors_p = [], []
    for n in (4, 8, 16, 32):
        qs, p_end = _midpoint(term, 0.0, h, [q0], [p0], n)
        assert qs.shape == (n + 1, 1)
        assert float(qs[0, 0]) == q0
        errors_q.append(abs(float(qs[-1, 0]) - q_exact))
        errors_p.append(abs(float(p_end[0]) - p_exact))
    for errors in (errors_q, errors_p):
        for e0, e1 in zip(errors, errors[1:], strict=False):
            assert 3.5 < e0 / e1 < 4.5, errors
    assert errors_q[-1] < 1e-4


def test_implicit_midpoint_intermediate_labels_on_grid():
    term = LagrangianTerm(oscillator)
    n, h = 64, 0.8
    qs, _ = _midpoint(term, 0.0, h, [1.0], [0.0], n)
    exact = np.cos(h * np.arange(n + 1) / n)
    np.testing.assert_allclose(np.asarray(qs[:, 0]), exact, atol=1e-4)


def test_implicit_midpoint_degenerate_pendulum():
    problem = problems.pendulum()
    q0, p0 = problem.y0
    h, n = 0.5, 10
    qs, p_end = _midpoint(problem.term, problem.t0, h, q0, p0, n, iterations=4)
    assert qs.shape == (n + 1, 2)
    assert bool(jnp.all(jnp.isfinite(qs))) and bool(jnp.all(jnp.isfinite(p_end)))
    q_ref, p_ref = problem.reference(np.asarray([problem.t0 + h]))
    np.testing.assert_allclose(np.asarray(qs[-1]), q_ref[0], atol=1e-3)
    np.testing.assert_allclose(np.asarray(p_end), p_ref[0], atol=1e-3)
    # The constraint p₂ = 0 of the degenerate Lagrangian is kept (f₂ vanishes at the midpoint).
    assert abs(float(p_end[1])) < 1e-12
    # And it converges with the second order of the midpoint rule.
    qs2, _ = _midpoint(problem.term, problem.t0, h, q0, p0, 2 * n, iterations=4)
    e1 = np.max(np.abs(np.asarray(qs[-1]) - q_ref[0]))
    e2 = np.max(np.abs(np.asarray(qs2[-1]) - q_ref[0]))
    assert 3.0 < e1 / e2 < 5.0


def time_dependent(t, q, v, args):
    return jnp.sum(0.5 * v**2 - 0.5 * q**2 * (1 + t))


def test_implicit_midpoint_starts_at_given_time():
    term = LagrangianTerm(time_dependent)
    at0 = _midpoint(term, 0.0, 0.5, [0.5], [0.2], 8)
    at5 = _midpoint(term, 5.0, 0.5, [0.5], [0.2], 8)
    assert abs(float(at0[0][-1, 0]) - float(at5[0][-1, 0])) > 1e-3
    # Starting at t = 5 is the same as starting at 0 with the Lagrangian shifted by 5.
    shifted = LagrangianTerm(lambda t, q, v, args: time_dependent(t + 5.0, q, v, args))
    ref = _midpoint(shifted, 0.0, 0.5, [0.5], [0.2], 8)
    np.testing.assert_allclose(np.asarray(at5[0]), np.asarray(ref[0]), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(np.asarray(at5[1]), np.asarray(ref[1]), rtol=1e-13, atol=1e-15)


def test_implicit_midpoint_float32():
    term = LagrangianTerm(oscillator)
    qs, p_end = _midpoint(term, 0.0, 1.0, [0.5], [0.3], 8, dtype=jnp.float32)
    assert qs.dtype == jnp.float32 and p_end.dtype == jnp.float32
    assert abs(float(qs[-1, 0]) - (0.5 * math.cos(1.0) + 0.3 * math.sin(1.0))) < 1e-2


def test_implicit_midpoint_iode_oscillator_matches_lagrangian():
    iode = IODETerm(lambda t, q, v, a: v, lambda t, q, v, a: -q)
    lag = LagrangianTerm(oscillator)
    a = _midpoint(iode, 0.0, 1.0, [0.5], [0.3], 6)
    b = _midpoint(lag, 0.0, 1.0, [0.5], [0.3], 6)
    np.testing.assert_allclose(np.asarray(a[0]), np.asarray(b[0]), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(a[1]), np.asarray(b[1]), rtol=1e-14)


def test_with_substeps_keeps_every_other_option():
    """The reference's `extrapolation_substep` changes the sub-steps only (it once dropped a
    `PreviousStep`'s tolerance)."""
    import diffrax_vi as dvi

    warm = dvi.PreviousStep(first=dvi.HermiteExtrapolation(4), tolerance=1e-3)
    changed = warm.with_substeps(12)
    assert changed.tolerance == 1e-3
    assert changed.first == dvi.HermiteExtrapolation(12)
    assert dvi.IntegratorExtrapolation(4, 7).with_substeps(6) == dvi.IntegratorExtrapolation(6, 7)
    assert dvi.NoExtrapolation(4).with_substeps(8) == dvi.NoExtrapolation(8)
    method = dvi.ShallowNet(dvi.ShallowNetBasis(dvi.tanh, 4), dvi.GaussLegendre(4),
                            initial_trajectory_method=warm, extrapolation_substep=12)
    assert method.seed.initial_trajectory == changed


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32, jnp.float16])
@pytest.mark.parametrize("count", [2, 3, 17, 33])
def test_labels_curve_is_jnp_interp_on_the_uniform_grid(dtype, count):
    """The trajectory seed's curve (the projected step's restart) takes its interval from
    the grid's arithmetic instead of a search: compiled, its values and τ-slopes are those
    of `jnp.interp` bit for bit, at the grid's own points, the ends, Gauss–Legendre nodes
    (0.5 among them), between, and outside [0, 1]."""
    labels = jnp.asarray(np.random.default_rng(count).normal(size=(count, 3)), dtype)
    grid = jnp.arange(count, dtype=dtype) / (count - 1)
    taus = np.concatenate([
        np.asarray(grid, np.float64), [0.0, 1.0, 0.5, -0.1, 1.1], np.linspace(0, 1, 41),
        *(np.asarray(GaussLegendre(r).nodes_weights(jnp.float64)[0]) for r in (3, 8, 16)),
    ])
    taus = jnp.asarray(taus, dtype)

    def with_slope(curve):
        return jax.jit(jax.vmap(lambda t: jax.jvp(curve, (t,), (jnp.ones_like(t),))))(taus)

    ours = with_slope(labels_curve(labels))
    reference = with_slope(
        lambda t: jax.vmap(lambda y: jnp.interp(t, grid, y), in_axes=1)(labels)
    )
    for a, b in zip(ours, reference, strict=True):
        assert a.dtype == dtype
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_labels_curve_refuses_a_single_label():
    with pytest.raises(ValueError, match="at least two labels"):
        labels_curve(jnp.zeros((1, 2)))
