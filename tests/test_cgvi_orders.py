"""`CGVI(s)` has order 2s, measured for s = 1..12 on the harmonic oscillator (issue 28).

The error of each run is compared with the same run in exact arithmetic: the one-step map of
the cGVI on the oscillator, computed in extended precision from the Galerkin action
(`diffrax_vi._spectral`). The table is on the studies page.

Step sizes: float64 runs of `CGVI(s)` carry a systematic rounding drift of the phase of
about `1e-15 · ωh` per step. Each degree is measured at the smallest `ωh2` (grid 0.01) at
which the exact-arithmetic error is at least 300 times `2e-15 · ωh2` per step, and at
`1.25 ωh2`, so rounding moves the fitted order by less than 0.03. For s >= 10 those steps are
outside the asymptotic regime (the exact-arithmetic order there is 2s - 0.6 ... 2s - 1.2):
an order within 0.5 of 2s cannot be observed above float64 rounding. For those degrees the
order rests on the two other tests: the float64 errors are those of the method in exact
arithmetic (to 1 %), and the method's exact-arithmetic order at small steps is 2s.
"""

import jax

jax.config.update("jax_enable_x64", True)

import functools  # noqa: E402

import diffrax  # noqa: E402
import mpmath  # noqa: E402
import pytest  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import _spectral as spectral  # noqa: E402
from diffrax_vi import problems  # noqa: E402

N1, N2 = 160, 200  # steps over the same span
OMEGA = mpmath.sqrt(mpmath.mpf(1) / 2)  # the oscillator's frequency
AMPLITUDE = mpmath.mpf("0.5")
# ωh2 per degree, by the rule of the cgvi_orders study (docs/studies.md).
DESIGN = {1: 0.01, 2: 0.01, 3: 0.08, 4: 0.28, 5: 0.65, 6: 1.18, 7: 1.86, 8: 2.66, 9: 3.56,
          10: 4.55, 11: 5.62, 12: 6.75}
ASYMPTOTIC = range(1, 10)  # degrees whose design steps are in the asymptotic regime
LARGE_STEP = 3.0  # ωh above which the measurement takes the large-step root finder


def exact_arithmetic_error(degree, x, steps):
    with mpmath.workdps(60):
        discrete, exact = spectral.oscillator_map(degree, x)
        y0 = mpmath.matrix([AMPLITUDE, 0])
        return mpmath.norm(discrete**steps * y0 - exact**steps * y0) / AMPLITUDE


@functools.cache
def measure(degree):
    """Errors at the two step sizes, measured and in exact arithmetic, and the step ratio."""
    problem = problems.harmonic_oscillator()
    h2 = DESIGN[degree] / float(OMEGA)
    span = N2 * h2
    h1 = span / N1
    # CGVI's default, the Jacobian-free iteration, contracts at a rate of order (ωh)²: the
    # steps of the high degrees take SpectralCGVI's root finder for large steps
    options = ({"root_finder": spectral.large_step_root_finder()}
               if DESIGN[degree] > LARGE_STEP else {})
    solve = jax.jit(lambda h: diffrax.diffeqsolve(
        problem.term, dvi.CGVI(degree, **options), 0.0, span, h, problem.y0, args=problem.args,
        max_steps=N2 + 2,
    ).ys)  # fmt: skip
    errors = []
    for h in (h1, h2):
        q, p = solve(h)
        q, p = mpmath.mpf(float(q[-1, 0])), mpmath.mpf(float(p[-1, 0]))
        with mpmath.workdps(40):
            phase = mpmath.mpf(span) * OMEGA
            dq, dp = q - AMPLITUDE * mpmath.cos(phase), p / OMEGA + AMPLITUDE * mpmath.sin(phase)
            errors.append(mpmath.sqrt(dq**2 + dp**2) / AMPLITUDE)
    exact = [exact_arithmetic_error(degree, mpmath.mpf(h) * OMEGA, n)
             for h, n in ((h1, N1), (h2, N2))]
    return errors, exact, mpmath.log(mpmath.mpf(h1) / h2)


def fitted_orders(degree):
    errors, exact, log_ratio = measure(degree)
    return (float(mpmath.log(errors[0] / errors[1]) / log_ratio),
            float(mpmath.log(exact[0] / exact[1]) / log_ratio))


def _marks(degree):
    return [pytest.mark.slow] if degree > 6 else []


DEGREES = [pytest.param(s, marks=_marks(s)) for s in range(1, 13)]


@pytest.mark.parametrize("degree", DEGREES)
def test_cgvi_errors_are_those_of_the_method_in_exact_arithmetic(degree):
    errors, exact, _ = measure(degree)
    for measured, ideal in zip(errors, exact, strict=True):
        # By the choice of steps the rounding is at most 1/300 of the error.
        assert abs(measured / ideal - 1) <= 0.01
    order, order_exact = fitted_orders(degree)
    assert abs(order - order_exact) <= 0.05


@pytest.mark.parametrize("degree", [pytest.param(s, marks=_marks(s)) for s in ASYMPTOTIC])
def test_cgvi_observed_order_is_two_s(degree):
    order, _ = fitted_orders(degree)
    assert 2 * degree - 0.5 <= order <= 2 * degree + 0.5


@pytest.mark.parametrize("degree", range(1, 13))
def test_cgvi_exact_arithmetic_order_is_two_s(degree):
    # The phase error per unit time of the method in exact arithmetic at small steps.
    with mpmath.workdps(75):
        def rate(x):
            discrete, _ = spectral.oscillator_map(degree, x, digits=75)
            return abs(mpmath.acos(discrete[0, 0]) - x) / x

        x1, x2 = mpmath.mpf("0.05"), mpmath.mpf("0.04")
        order = mpmath.log(rate(x1) / rate(x2)) / mpmath.log(x1 / x2)
    assert abs(float(order) - 2 * degree) <= 0.01
