"""Compensated summation of the state (issue 28): increments to their own rounding, exact
TwoSum, and what it buys on long runs with small steps."""

from fractions import Fraction

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._precision import two_sum


def test_two_sum_is_exact():
    rng = np.random.default_rng(0)
    a = rng.normal(size=2000) * 10.0 ** rng.integers(-20, 20, size=2000)
    b = rng.normal(size=2000) * 10.0 ** rng.integers(-20, 20, size=2000)
    s, e = jax.jit(two_sum)(jnp.asarray(a), jnp.asarray(b))
    for x, y, sx, ex in zip(a, b, np.asarray(s), np.asarray(e), strict=True):
        assert Fraction(float(x)) + Fraction(float(y)) == Fraction(float(sx)) + Fraction(float(ex))
        assert sx == x + y


def _energy_errors(problem, solver, h, steps, dtype=jnp.float64, phases=(None,)):
    """The maximum relative energy error over 201 times of a run from each start: the
    problem's (`None`), or the oscillator's state of the same energy at phase `φ`."""
    ts = jnp.asarray(np.linspace(0.0, steps * h, 201), dtype)

    @jax.jit
    def solve(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, ts[0], ts[-1], jnp.asarray(h, dtype), y0, args=problem.args,
            saveat=diffrax.SaveAt(ts=ts, solver_state=True), max_steps=steps + 10,
        )

    energy = jax.vmap(lambda q, p: problem.energy(0.0, q, p))
    errors, sols = [], []
    for phase in phases:
        y0 = problem.y0
        if phase is not None:  # the oscillator's defaults: m = 1, k = 0.5
            a = float(problem.y0[0][0])
            y0 = (jnp.array([a * np.cos(phase)]), jnp.array([-a * np.sqrt(0.5) * np.sin(phase)]))
        y0 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), y0)
        sol = solve(y0)
        assert sol.result == diffrax.RESULTS.successful
        e = np.asarray(energy(*jax.tree_util.tree_map(lambda a: a.astype(jnp.float64), sol.ys)))
        e0 = float(problem.energy(0.0, *jax.tree_util.tree_map(
            lambda a: a.astype(jnp.float64), y0)))
        errors.append(np.max(np.abs(e - e0) / abs(e0)))
        sols.append(sol)
    return errors, sols


def _energy_error(problem, solver, h, steps, dtype=jnp.float64):
    (error,), (sol,) = _energy_errors(problem, solver, h, steps, dtype)
    return error, sol


def test_compensation_keeps_small_steps_at_round_off():
    # Small steps: the increments are far below the state, so plain sums lose eps·|y| per
    # step and the compensated ones do not (oscillator, h = 0.05, 4·10^4 steps). The maximum
    # error of one run is one draw of a random walk: compare the medians over six phases.
    problem = problems.harmonic_oscillator()
    phases = (None, 0.7, 1.9, 3.1, 4.4, 5.6)
    plain, _ = _energy_errors(problem, dvi.CGVI(6, compensated=False), 0.05, 40_000,
                              phases=phases)
    compensated, sols = _energy_errors(problem, dvi.CGVI(6), 0.05, 40_000, phases=phases)
    assert np.median(compensated) <= 5e-15
    assert np.median(compensated) <= np.median(plain) / 4
    sol = sols[0]
    # what is carried is the rounding of the last sums: at most half an ulp of the state
    q, p = (a[-1] for a in sol.ys)
    eq, ep = (a[-1] for a in sol.solver_state.compensation)
    assert bool(jnp.all(jnp.abs(eq) <= jnp.spacing(jnp.abs(q)) / 2))
    assert bool(jnp.all(jnp.abs(ep) <= jnp.spacing(jnp.abs(p)) / 2))
    assert bool(jnp.any(eq != 0) | jnp.any(ep != 0))


@pytest.mark.slow  # compensation: the float64 test above; here its float32 run (20 000 steps)
@pytest.mark.parametrize("dtype, bound", [(jnp.float32, 2e-6)])
def test_float32_stays_float32_with_compensation(dtype, bound):
    problem = problems.harmonic_oscillator()
    plain, _ = _energy_error(problem, dvi.CGVI(4, compensated=False), 0.05, 20_000, dtype)
    compensated, sol = _energy_error(problem, dvi.CGVI(4), 0.05, 20_000, dtype)
    assert sol.ys[0].dtype == dtype and sol.ys[1].dtype == dtype
    assert all(a.dtype == dtype for a in sol.solver_state.compensation)
    assert compensated <= bound
    assert compensated <= plain / 4


def test_uncompensated_carries_nothing():
    problem = problems.harmonic_oscillator()
    _, sol = _energy_error(problem, dvi.CGVI(4, compensated=False), 0.1, 100)
    assert all(bool(jnp.all(a == 0)) for a in sol.solver_state.compensation)


def test_constant_step_times_are_not_accumulated():
    # diffrax's ConstantStepSize places step n at t0 + (t1 - t0)·n/N, so the times carry no
    # summed rounding: the solver needs no compensation of t.
    h = 2 * np.pi / 100
    steps = 20_000
    sol = diffrax.diffeqsolve(
        dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 0.5 * q @ q), dvi.CGVI(2),
        0.0, steps * h, h, (jnp.array([0.5]), jnp.array([0.0])),
        saveat=diffrax.SaveAt(steps=True), max_steps=steps,
    )
    ts = np.asarray(sol.ts)
    exact = [float(Fraction(steps * h) * k / steps) for k in range(1, steps + 1)]
    assert np.max(np.abs(ts - exact) / np.spacing(np.abs(exact))) <= 1


def test_compensated_must_be_a_bool():
    with pytest.raises(TypeError, match="compensated"):
        dvi.CGVI(3, compensated="yes")


def test_precision_vocabulary():
    from diffrax_vi._precision import compensated_add, floating_dtype, lapack_dtype

    assert lapack_dtype(jnp.float16) == np.float32 and lapack_dtype(jnp.float64) == np.float64
    assert floating_dtype(jnp.ones(2, jnp.float16)) == np.float16
    assert floating_dtype(jnp.ones(2, jnp.int32)) == jnp.result_type(float)
    x, carried = jnp.float32(1.0), jnp.float32(0.0)
    s, e = compensated_add(x, jnp.float64(2.0**-30), carried)
    assert s.dtype == jnp.float32 and float(s) + float(e) == 1.0 + 2.0**-30
