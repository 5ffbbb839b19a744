"""Observed order of `CGVI(s)`, s = 1..12, on the harmonic oscillator (issue 28).

The oscillator `L = v²/2 − q²/4` (ω = 1/√2) from `(0.5, 0)`; the error is the distance of the
end state from the exact one in the coordinates `(q, p/ω)`, relative to the amplitude. Two
runs per degree over the same span, with N1 = 160 and N2 = 200 constant steps (ratio 1.25),
and the order fitted from the two errors. Next to each measurement: the same error in exact
arithmetic, from the one-step map of the cGVI on the oscillator computed in extended precision
(`diffrax_vi.spectral`), and its two-point order.

Step sizes: `CGVI(s)` shifts the phase by a systematic rounding error of about
`1e-15 · ωh` per step (measured below as `rounding per step`: the difference between the
float64 run and exact arithmetic, per step). The smaller step `ωh2` is the smallest on a grid
of 0.01 at which the exact-arithmetic error is at least 300 times `2e-15 · ωh2` per step, so
the rounding moves the fitted order by less than 0.03; the larger step is `1.25 ωh2`.
Where this rule needs large steps the fit is pre-asymptotic: the exact-arithmetic column
shows how far.

A last table gives the exact-arithmetic order at small steps (ωh = 0.05 and 0.04, phase
error per unit time): the asymptotic order.

    taskset -c 0 .venv/bin/python -m benchmarks.cgvi_orders \\
        > benchmarks/results/cgvi_orders.txt
"""

from __future__ import annotations

import argparse
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import mpmath  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems, spectral  # noqa: E402

N1, N2 = 160, 200
FLOOR_PER_STEP = 2e-15  # times ωh: the rounding drift bound the design rule assumes
RATIO = 300
OMEGA = mpmath.sqrt(mpmath.mpf(1) / 2)
AMPLITUDE = mpmath.mpf("0.5")


def exact_arithmetic_error(degree: int, x, steps: int):
    """Relative end-state error of `CGVI(degree)` after `steps` steps of `ωh = x`, in exact
    arithmetic (extended precision)."""
    with mpmath.workdps(60):
        discrete, exact = spectral.oscillator_map(degree, x)
        y0 = mpmath.matrix([AMPLITUDE, 0])
        return mpmath.norm(discrete**steps * y0 - exact**steps * y0) / AMPLITUDE


def design(degree: int) -> float:
    """The smaller step `ωh2` of the design rule (grid of 0.01)."""
    for k in range(1, 2000):
        x2 = k / 100
        if exact_arithmetic_error(degree, x2, N2) >= RATIO * FLOOR_PER_STEP * x2 * N2:
            return x2
    raise RuntimeError(f"no design for degree {degree}")


def measured_error(solve, h: float, span: float):
    q, p = solve(h, span)
    q, p = mpmath.mpf(float(q[-1, 0])), mpmath.mpf(float(p[-1, 0]))
    with mpmath.workdps(40):
        phase = mpmath.mpf(span) * OMEGA
        dq = q - AMPLITUDE * mpmath.cos(phase)
        dp = p / OMEGA + AMPLITUDE * mpmath.sin(phase)
        return mpmath.sqrt(dq**2 + dp**2) / AMPLITUDE


def asymptotic_order(degree: int) -> float:
    """Two-point slope of the exact-arithmetic phase error per unit time at ωh = 0.05 and
    0.04 (75 digits: the errors reach 1e-60)."""
    with mpmath.workdps(75):
        def phase_rate(x):
            discrete, _ = spectral.oscillator_map(degree, x, digits=75)
            return abs(mpmath.acos(discrete[0, 0]) - x) / x

        x1, x2 = mpmath.mpf("0.05"), mpmath.mpf("0.04")
        return float(mpmath.log(phase_rate(x1) / phase_rate(x2)) / mpmath.log(x1 / x2))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--degrees", type=int, nargs="*", default=list(range(1, 13)))
    args = parser.parse_args(argv)
    problem = problems.harmonic_oscillator()
    omega = float(OMEGA)
    print(f"CGVI(s) on the harmonic oscillator, omega = 1/sqrt(2), {N1} and {N2} steps over "
          "the same span, float64\n")
    print("| s | omega*h1 | omega*h2 | error h1 | error h2 | fitted order | exact-arithmetic "
          "order | error / exact-arithmetic error (h2) | rounding per step (h2) | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for degree in args.degrees:
        start = time.perf_counter()
        x2 = design(degree)
        h2 = x2 / omega
        span = N2 * h2
        h1 = span / N1
        solver = dvi.CGVI(degree)
        solve = jax.jit(lambda h, t1, solver=solver: diffrax.diffeqsolve(
            problem.term, solver, 0.0, t1, h, problem.y0, args=problem.args,
            max_steps=N2 + 2,
        ).ys)  # fmt: skip
        e1, e2 = measured_error(solve, h1, span), measured_error(solve, h2, span)
        m1 = exact_arithmetic_error(degree, mpmath.mpf(h1) * OMEGA, N1)
        m2 = exact_arithmetic_error(degree, mpmath.mpf(h2) * OMEGA, N2)
        ratio = mpmath.log(mpmath.mpf(h1) / h2)
        order = float(mpmath.log(e1 / e2) / ratio)
        order_exact = float(mpmath.log(m1 / m2) / ratio)
        rounding = float(abs(e2 - m2) / N2)
        seconds = time.perf_counter() - start
        print(f"| {degree} | {h1 * omega:.4g} | {h2 * omega:.4g} | {float(e1):.3e} | "
              f"{float(e2):.3e} | {order:.3f} | {order_exact:.3f} | {float(e2 / m2):.4f} | "
              f"{rounding:.1e} | {seconds:.1f} |", flush=True)
        print(f"done {degree}", file=sys.stderr, flush=True)
    print("\nExact-arithmetic order at small steps (phase error per unit time at omega*h = 0.05 "
          "and 0.04):\n")
    print("| s | " + " | ".join(str(s) for s in args.degrees) + " |")
    print("|---|" + "---|" * len(args.degrees))
    print("| order | " + " | ".join(f"{asymptotic_order(s):.3f}" for s in args.degrees) + " |")


if __name__ == "__main__":
    main()
