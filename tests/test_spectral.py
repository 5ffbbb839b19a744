"""Spectral variant of CGVI: a fixed large step, the degree raised until the step is resolved
(issue 28; Hall and Leok 2015)."""

import jax

jax.config.update("jax_enable_x64", True)

import functools  # noqa: E402
import math  # noqa: E402

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi._spectral import (  # noqa: E402
    DEFAULT_RTOL,
    SpectralCGVI,
    large_step_root_finder,
    spectral_degree,
    spectral_step_error,
)

STEPS = (1.0, 2.0, math.pi)  # ω h on the oscillator with ω = 1
DEGREES = (2, 4, 6, 8)


def one_step(problem, solver, h, q0, p0):
    """One step of `h[i]` from each start `(q0[i], p0[i])`, in one compiled, vmapped solve."""
    def step(h, q, p):
        sol = diffrax.diffeqsolve(problem.term, solver, 0.0, h, h, (q, p), args=problem.args,
                                  max_steps=2)
        return sol.ys[0][-1], sol.ys[1][-1]

    h = jnp.broadcast_to(jnp.asarray(h, jnp.float64), (len(q0),))
    return jax.jit(jax.vmap(step))(h, jnp.asarray(q0), jnp.asarray(p0))


@functools.cache
def oscillator_errors(degree):
    """One-step errors of CGVI(degree) on the oscillator (ω = 1) from the unit states
    (1, 0) and (0, 1), for each step in STEPS: the largest of the two per step."""
    problem = problems.harmonic_oscillator(k=1.0, q0=1.0)
    h = np.repeat(STEPS, 2)
    q0, p0 = np.tile([[1.0], [0.0]], (len(STEPS), 1)), np.tile([[0.0], [1.0]], (len(STEPS), 1))
    solver = dvi.CGVI(degree, root_finder=large_step_root_finder())  # SpectralCGVI's
    q, p = (np.asarray(a)[:, 0] for a in one_step(problem, solver, h, q0, p0))
    # The exact flow: rotation by h in (q, p).
    err = np.hypot(q - (q0[:, 0] * np.cos(h) + p0[:, 0] * np.sin(h)),
                   p - (p0[:, 0] * np.cos(h) - q0[:, 0] * np.sin(h)))
    return [float(e) for e in err.reshape(len(STEPS), 2).max(axis=1)]


@pytest.mark.parametrize("degree", DEGREES)
def test_oscillator_error_is_the_exact_arithmetic_estimate(degree):
    # The oscillator model is the spectral norm of (method − flow); the largest error over
    # the two unit starts lies between it/√2 and it. Rounding: below 1e-14 per step.
    for h, measured in zip(STEPS, oscillator_errors(degree), strict=True):
        model = spectral_step_error(degree, h, 1.0, model="oscillator")
        assert measured <= model * 1.01 + 1e-14, (h, measured, model)
        if model > 1e-12:
            assert measured >= model / math.sqrt(2) * 0.99, (h, measured, model)


@pytest.mark.parametrize("h", STEPS)
def test_error_falls_geometrically_in_the_degree(h):
    errors = [oscillator_errors(d)[STEPS.index(h)] for d in DEGREES]
    above = [e for e in errors if e > 1e-12]  # above rounding
    assert len(above) >= 2
    # Every two degrees the error falls by at least a factor 10 (measured: 24 and more).
    for a, b in zip(above, above[1:], strict=False):
        assert b <= a / 10, errors


@pytest.mark.parametrize("model", ["analytic", "oscillator"])
@pytest.mark.parametrize("h, rtol", [(math.pi, 1e-6), (2.0, 1e-9), (1.0, 1e-12)])
def test_chosen_degree_meets_rtol_on_the_oscillator(h, rtol, model):
    degree = spectral_degree(h, 1.0, rtol, model=model)
    assert spectral_step_error(degree, h, 1.0, model) <= rtol
    if degree > 1:
        assert spectral_step_error(degree - 1, h, 1.0, model) > rtol
    exact = spectral_step_error(degree, h, 1.0, model="oscillator")
    assert exact <= rtol  # the analytic model is conservative for the oscillator
    if model == "oscillator" and degree in DEGREES:
        assert oscillator_errors(degree)[STEPS.index(h)] <= rtol


def test_chosen_degree_meets_rtol_on_kepler_at_a_large_step():
    # Kepler, e = 0.5, eight steps per orbit; time scale: the pericentre passage r_p/|v_p|.
    e, rtol = 0.5, 1e-6
    problem = problems.kepler(e)
    h = 2 * math.pi / 8
    timescale = (1 - e) ** 1.5 / math.sqrt(1 + e)
    solver = SpectralCGVI(h, timescale, rtol)
    degree = spectral_degree(h, timescale, rtol)
    assert solver.basis.degree == degree and solver.quadrature.n == degree + 1
    starts = np.linspace(0.0, 2 * math.pi, 32, endpoint=False)
    q0, p0 = problem.reference(starts)
    q1, p1 = problem.reference(starts + h)
    q, p = one_step(problem, solver, h, q0, p0)
    y0, y1 = np.concatenate([q0, p0], 1), np.concatenate([q1, p1], 1)
    err = np.linalg.norm(np.concatenate([q, p], 1) - y1, axis=1) / np.linalg.norm(y0, axis=1)
    assert float(err.max()) <= rtol
    # The oscillator model would have chosen too low a degree here (orbits have singularities
    # in complex time; their error falls only geometrically in the degree).
    assert spectral_degree(h, timescale, rtol, model="oscillator") < degree


def test_spectral_cgvi_is_a_cgvi_of_the_chosen_degree():
    solver = SpectralCGVI(math.pi, 1.0, 1e-6, model="oscillator")
    assert isinstance(solver, dvi.NetworkVI)
    assert solver.basis == dvi.LagrangeBasis(6) and solver.quadrature == dvi.GaussLegendre(7)
    assert spectral_degree(math.pi, 1.0, 1e-6, model="oscillator") == 6
    assert spectral_degree(math.pi, 1.0) == spectral_degree(math.pi, 1.0, DEFAULT_RTOL)
    options = SpectralCGVI(1.0, 1.0, 1e-6, root_finder=dvi.RoundoffNewton(ftol=0.0))
    assert options.root_finder == dvi.RoundoffNewton(ftol=0.0)


@pytest.mark.parametrize("bad", [0, -1.0, math.nan, math.inf, True, "1", None, [1.0]])
def test_refuses_invalid_steps_and_time_scales(bad):
    with pytest.raises(ValueError, match="dt must be a positive"):
        spectral_degree(bad, 1.0)
    with pytest.raises(ValueError, match="timescale must be a positive"):
        SpectralCGVI(1.0, bad)


@pytest.mark.parametrize("rtol", [0.0, -1e-8, 1.0, 2.0, 1e-40, math.nan, "1e-8"])
def test_refuses_invalid_tolerances(rtol):
    with pytest.raises(ValueError, match="rtol"):
        spectral_degree(1.0, 1.0, rtol)


def test_refuses_other_arguments():
    with pytest.raises(ValueError, match="max_degree must be an integer"):
        spectral_degree(1.0, 1.0, 1e-8, max_degree=0)
    with pytest.raises(ValueError, match="max_degree must be an integer"):
        spectral_degree(1.0, 1.0, 1e-8, max_degree=2.5)
    with pytest.raises(ValueError, match="model must be one of"):
        spectral_degree(1.0, 1.0, 1e-8, model="chebyshev")
    with pytest.raises(ValueError, match="degree must be an integer"):
        spectral_step_error(0, 1.0, 1.0)
    with pytest.raises(ValueError, match="chooses its own quadrature"):
        SpectralCGVI(1.0, 1.0, quadrature=dvi.GaussLegendre(4))


def test_refuses_a_step_no_allowed_degree_resolves():
    with pytest.raises(ValueError, match=r"no degree up to max_degree=5 .* the best is degree 5"):
        spectral_degree(math.pi, 1.0, 1e-12, max_degree=5)
