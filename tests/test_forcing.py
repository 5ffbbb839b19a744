"""Non-conservative forces in the variational step (Lagrange–d'Alembert): `LagrangianTerm(L,
force=F)` against the closed-form damped and driven oscillators."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems

jax.config.update("jax_enable_x64", True)

ENGINE = dvi.ChordIteration(ftol=0.0, predict=True, picard=True)


def _final_error(problem, solver, steps: int) -> float:
    """Largest error of `(q, p)` at `problem.t1` after `steps` constant steps."""
    # The step as an array and one step cap: runs of up to 252 steps share one compiled
    # program.
    h = jnp.asarray((problem.t1 - problem.t0) / steps)
    sol = diffrax.diffeqsolve(problem.term, solver, problem.t0, problem.t1, h, problem.y0,
                              max_steps=max(256, steps + 4),
                              saveat=diffrax.SaveAt(t1=True))
    q, p = problem.reference(np.array([problem.t1]))
    return max(float(np.max(np.abs(np.asarray(sol.ys[0][-1]) - q[-1]))),
               float(np.max(np.abs(np.asarray(sol.ys[1][-1]) - p[-1]))))


@pytest.mark.parametrize("degree", [2, 3])
def test_forced_cgvi_converges_at_order_twice_its_degree(degree):
    # damped and driven at once: m q'' = -k q - c q' + A cos(W t)
    problem = problems.forced_oscillator(damping=0.2, amplitude=0.5, frequency=0.7, t1=10.0)
    coarse, fine = (_final_error(problem, dvi.CGVI(degree), n) for n in (50, 100))
    order = np.log2(coarse / fine)
    assert order >= 2 * degree - 0.3, (coarse, fine, order)


@pytest.mark.parametrize("name", ["damped_oscillator", "driven_oscillator"])
def test_forced_oscillators_reach_round_off(name):
    problem = getattr(problems, name)(t1=10.0)
    assert _final_error(problem, dvi.CGVI(4), 100) <= 1e-12


def test_every_solver_sees_the_force():
    problem = problems.damped_oscillator(t1=10.0)
    # the Jacobian-free engine, the default network step, and an explicit solver (Hamilton's
    # equations with p' = dL/dq + F)
    assert _final_error(problem, dvi.CGVI(6, root_finder=ENGINE), 100) <= 1e-12
    assert _final_error(problem, dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10)), 100) <= 1e-12
    sol = diffrax.diffeqsolve(problem.term, diffrax.Dopri8(), problem.t0, problem.t1, 0.1,
                              problem.y0, stepsize_controller=diffrax.PIDController(
                                  rtol=1e-12, atol=1e-12))
    q, _ = problem.reference(np.array([problem.t1]))
    assert abs(float(sol.ys[0][-1, 0]) - q[-1, 0]) <= 1e-10
    # the damping takes the energy away (to e^{-ct} of it, to leading order)
    start = float(problem.energy(problem.t0, *problem.y0))
    end = float(problem.energy(problem.t1, sol.ys[0][-1], sol.ys[1][-1]))
    assert end < 0.5 * start


def test_a_zero_force_is_the_conservative_run_to_the_bit():
    def lagrangian(t, q, v, args):
        return 0.5 * v @ v - 0.5 * q @ q - 0.1 * q[0] ** 4

    y0 = (jnp.array([0.5, -0.2]), jnp.array([0.1, 0.3]))
    runs = []
    for term in (dvi.LagrangianTerm(lagrangian),
                 dvi.LagrangianTerm(lagrangian, force=lambda t, q, v, args: jnp.zeros_like(q))):
        sol = diffrax.diffeqsolve(term, dvi.CGVI(3), 0.0, 2.0, 0.1, y0)
        runs.append(np.asarray(jnp.concatenate(sol.ys, axis=-1)))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_gradient_through_a_forced_run_matches_finite_differences():
    term = dvi.LagrangianTerm(lambda t, q, v, c: 0.5 * v @ v - 0.5 * q @ q,
                              force=lambda t, q, v, c: -c * v)
    solver = dvi.CGVI(4)

    def final(c):
        sol = diffrax.diffeqsolve(term, solver, 0.0, 3.0, 0.1, (jnp.ones(1), jnp.zeros(1)),
                                  args=c, saveat=diffrax.SaveAt(t1=True))
        return sol.ys[0][-1, 0]

    c, d = 0.3, 1e-6
    gradient = float(jax.grad(final)(c))
    difference = float((final(c + d) - final(c - d)) / (2 * d))
    np.testing.assert_allclose(gradient, difference, rtol=1e-6)


@pytest.mark.parametrize(
    "force, error, match",
    [
        (lambda t, q, v, args: -v[:1], ValueError, "shape"),
        (lambda t, q, v, args: jnp.zeros(q.shape, jnp.int32), ValueError, "dtype"),
        ("not a function", TypeError, "force must be callable"),
    ],
)
def test_a_malformed_force_is_refused_by_name(force, error, match):
    with pytest.raises(error, match=match):
        term = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v, force=force)
        diffrax.diffeqsolve(term, dvi.CGVI(2), 0.0, 0.2, 0.1, (jnp.ones(2), jnp.zeros(2)))
