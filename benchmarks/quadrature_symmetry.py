"""Gauss–Legendre coefficients with exact symmetries (issue 28): how far NumPy's coefficients
are from the true ones, what the extended-precision ones give, and whether it shows in the
energy of a long run.

1. Coefficients, n = 1..32: the largest error of NumPy's `leggauss` nodes and weights (mapped
   to `[0, 1]`) and of the package's against a 256-bit mpmath computation: nodes in units of
   2^-53 (the spacing of float64 on [1/2, 1), where the upper node of every symmetric pair
   lies), weights in units in the last place of the true weight; whether the nodes are
   symmetric (`c_i + c_{n+1-i} == 1`) and the weights equal in pairs; whether the weights sum
   to 1 exactly (as rationals), under `math.fsum`, under a left-to-right float64 sum and under
   `np.sum`. Then the same for float32 and float16 (rounded from extended precision).
2. Energy: `CGVI(7)` (or `--degree`) on the harmonic oscillator at h = 0.5, running maximum
   of the relative energy error at 10^1 ... 10^k steps and the growth exponent over the last
   two decades,
   with NumPy's coefficients (quadrature nodes, quadrature weights, Gauss–Lobatto points of
   the basis) swapped in by monkeypatching, alone and together; for the default initial
   state and, since one rounding history is one sample, as median and largest over
   `--batch` initial states of the same energy.

    taskset -c 0 .venv/bin/python -m benchmarks.quadrature_symmetry \\
        [--steps N] > benchmarks/results/quadrature_symmetry.txt
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from fractions import Fraction

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mpmath  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems, quadrature  # noqa: E402
from diffrax_vi.ansatz import polynomial  # noqa: E402

# the package's own rule, kept before `numpy_coefficients` swaps NumPy's in
PACKAGE_NODES_WEIGHTS = quadrature.GaussLegendre.nodes_weights


def package_rule(n: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    """The package's GL(n) nodes and weights on [0, 1] in `dtype`, as NumPy arrays."""
    c, b = PACKAGE_NODES_WEIGHTS(quadrature.GaussLegendre(n), np.dtype(dtype))
    return np.asarray(c), np.asarray(b)


def spacing_exponent(x, dtype) -> int:
    """The exponent `e` of the spacing `2**e` of `dtype` around the positive mpmath number
    `x` (subnormals included)."""
    info = np.finfo(dtype)
    with mpmath.workprec(256):
        _, exponent = mpmath.frexp(x)
    return max(int(exponent) - 1, int(info.minexp)) - int(info.nmant)


def exact_rule(n):
    """All nodes and weights of GL(n) on [0, 1] as mpmath numbers, increasing nodes."""
    nodes, weights = quadrature.gauss_legendre_exact(n)
    odd = n % 2
    lower = [1 - c for c in reversed(nodes[odd:])]
    return lower + list(nodes), list(reversed(weights[odd:])) + list(weights)


def ulps(values, exact, dtype):
    """|value - exact| in units of the spacing of `dtype` at the exact value."""
    out = []
    for v, x in zip(values, exact, strict=True):
        shift = spacing_exponent(x, dtype)
        with mpmath.workprec(256):
            out.append(float(abs(mpmath.mpf(float(v)) - x) / mpmath.ldexp(1, shift)))
    return max(out)


def absolute(values, exact):
    """max |value - exact| in units of 2^-53."""
    with mpmath.workprec(256):
        return max(float(abs(mpmath.mpf(float(v)) - x) * 2**53)
                   for v, x in zip(values, exact, strict=True))


def numpy_rule(n):
    x, w = np.polynomial.legendre.leggauss(n)
    c, b = 0.5 * (x + 1.0), 0.5 * w
    return c, b


def numpy_lobatto(degree):
    if degree == 1:
        return (0.0, 1.0)
    inner = np.polynomial.legendre.Legendre.basis(degree).deriv().roots()
    x = np.concatenate([[-1.0], np.sort(inner.real), [1.0]])
    return tuple(float(v) for v in 0.5 * (x + 1.0))


def sums(b, dtype):
    exact = sum((Fraction(float(v)) for v in b), Fraction(0)) == 1
    seq = dtype(0)
    for v in b:
        seq = dtype(seq + v)
    return exact, math.fsum(float(v) for v in b) == 1.0, seq == 1, np.sum(b) == dtype(1)


def coefficient_table():
    print("## Coefficients, float64 (node errors in units of 2^-53, weight errors in units in "
          "the last place of the true weight)\n")
    print("| n | numpy nodes | numpy weights | numpy symmetric | ours nodes | ours weights "
          "| ours symmetric | sum exact | fsum | left-to-right | np.sum |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    counts = np.zeros(4, int)
    for n in range(1, 33):
        c_ex, b_ex = exact_rule(n)
        cn, bn = numpy_rule(n)
        co, bo = package_rule(n, np.float64)
        sym_n = bool(np.all(cn + cn[::-1] == 1) and np.all(bn == bn[::-1]))
        sym_o = bool(np.all(co + co[::-1] == 1) and np.all(bo == bo[::-1]))
        s = sums(bo, np.float64)
        counts += s
        print(f"| {n} | {absolute(cn, c_ex):.2f} | {ulps(bn, b_ex, np.float64):.1f} | "
              f"{sym_n} | {absolute(co, c_ex):.2f} | {ulps(bo, b_ex, np.float64):.2f} | "
              f"{sym_o} | " + " | ".join(str(bool(v)) for v in s) + " |")
    print("\nsums equal to 1 out of 32 (exact, fsum, left-to-right, np.sum): "
          f"{[int(v) for v in counts]}")
    print("(ours: each node above 1/2 rounded to nearest, its partner below 1/2 is 1 - c; "
          "both sets are exactly symmetric)\n")
    for dtype in (np.float32, np.float16):
        counts = np.zeros(4, int)
        worst_w, asym = 0.0, 0
        for n in range(1, 33):
            c_ex, b_ex = exact_rule(n)
            c, b = package_rule(n, dtype)
            worst_w = max(worst_w, ulps(b, b_ex, dtype))
            asym += not (np.all(c + c[::-1] == 1) and np.all(b == b[::-1]))
            counts += sums(b, dtype)
        print(f"{np.dtype(dtype).name}: n = 1..32, rules not exactly symmetric: {asym}; "
              f"largest weight error {worst_w:.2f} ulp; sums equal to 1 (exact, fsum, "
              f"left-to-right, np.sum): {[int(v) for v in counts]}")
    print()


@contextlib.contextmanager
def numpy_coefficients(nodes: bool, weights: bool, points: bool):
    """Swap NumPy's Gauss–Legendre nodes, weights and/or Gauss–Lobatto points into the
    package (`nodes`/`weights`/`points` True: NumPy's; False: the package's own)."""
    saved = (quadrature.GaussLegendre.nodes_weights_np, quadrature.GaussLegendre.nodes_weights,
             polynomial.lobatto_points)

    def rule_np(self, dtype="float64"):
        ours = package_rule(self.n, dtype)
        theirs = (a.astype(dtype) for a in numpy_rule(self.n))
        return tuple(t if swap else o
                     for o, t, swap in zip(ours, theirs, (nodes, weights), strict=True))

    if nodes or weights:
        quadrature.GaussLegendre.nodes_weights_np = rule_np
        quadrature.GaussLegendre.nodes_weights = lambda self, dtype: tuple(
            jnp.asarray(a, dtype) for a in rule_np(self, dtype))
    if points:
        polynomial.lobatto_points = numpy_lobatto
    jax.clear_caches()  # programs compiled with the other constants must not be reused
    try:
        yield
    finally:
        (quadrature.GaussLegendre.nodes_weights_np, quadrature.GaussLegendre.nodes_weights,
         polynomial.lobatto_points) = saved
        jax.clear_caches()


def growth(ts, e, steps, h):
    """Running maximum of the relative energy error at each decade, and the log-log slope
    of the running maximum over the last two decades."""
    err = np.maximum.accumulate(np.abs(e - e[..., :1]) / np.abs(e[..., :1]), axis=-1)
    done = np.asarray(ts) / h
    decades = [10**k for k in range(1, int(np.log10(steps)) + 1)]
    at = np.stack([err[..., np.searchsorted(done, d)] for d in decades], axis=-1)
    tail = done >= steps / 100
    logs = np.log(np.maximum(err[..., tail], 1e-18))
    slope = np.polyfit(np.log(done[tail]), logs.reshape(-1, logs.shape[-1]).T, 1)[0]
    return at, slope.reshape(err.shape[:-1])


def energy_growth(steps: int, batch: int, degree: int = 7) -> None:
    problem = problems.harmonic_oscillator()
    h = 0.5
    marks = np.unique(np.round(np.geomspace(1, steps, 300)).astype(int))
    ts = jnp.asarray(np.concatenate([[0], marks]) * h)
    decades = [10**k for k in range(1, int(np.log10(steps)) + 1)]
    # Further initial states on the circle of the default energy: other rounding histories.
    phase = np.linspace(0.0, np.pi / 2, batch, endpoint=False)[1:]
    q0, p0 = (float(problem.y0[0][0]), float(problem.y0[1][0]))
    omega = np.sqrt(0.5)
    y0s = (jnp.asarray(q0 * np.cos(phase))[:, None],
           jnp.asarray(-q0 * omega * np.sin(phase) + p0)[:, None])
    energy = jax.vmap(jax.vmap(lambda q, p: problem.energy(0.0, q, p)))
    header = " | ".join(f"{d:g} steps" for d in decades)
    rows = []
    configs = [(False, False, False), (True, True, False), (True, False, False),
               (False, True, False), (False, False, True), (True, True, True)]
    for nodes, weights, points in configs:
        with numpy_coefficients(nodes, weights, points):
            solver = dvi.CGVI(degree)

            def run(y, solver=solver):
                return diffrax.diffeqsolve(
                    problem.term, solver, 0.0, steps * h, h, y, args=problem.args,
                    max_steps=steps, saveat=diffrax.SaveAt(ts=ts), throw=False,
                )

            one = jax.block_until_ready(jax.jit(run)(problem.y0))
            many = jax.block_until_ready(jax.jit(jax.vmap(run))(y0s)) if batch > 1 else None
        label = " | ".join("numpy" if v else "mpmath" for v in (nodes, weights, points))
        ok = bool(one.result == diffrax.RESULTS.successful)
        e1 = np.asarray(energy(one.ys[0][None], one.ys[1][None]))[0]
        at1, slope1 = growth(ts, e1, steps, h)
        row = [label, ok, at1, slope1, float(one.ys[0][-1, 0])]
        if many is not None:
            ok = ok and bool(np.all(np.asarray(many.result == diffrax.RESULTS.successful)))
            e = np.asarray(energy(many.ys[0], many.ys[1]))
            at, slope = growth(ts, np.concatenate([e1[None], e]), steps, h)
            row += [np.median(at, axis=0), np.max(at, axis=0), np.median(slope)]
        rows.append(row)
        print(f"done {label}", file=sys.stderr, flush=True)

    print(f"## Energy: CGVI({degree}), oscillator, h = {h}, {steps} steps, float64\n")
    print("Running maximum of the relative energy error; growth exponent: log-log slope of it "
          "over the last two decades. NumPy's coefficients (`leggauss` for the quadrature, "
          f"the roots of `P'_{degree}` for the Lobatto points of the basis) swapped in by "
          "monkeypatching.\n")
    print("Default initial state `(0.5, 0)`:\n")
    print(f"| GL nodes | GL weights | Lobatto points | {header} | growth exponent | q at the end |")
    print("|---|---|---|" + "---|" * (len(decades) + 2))
    for label, ok, at, slope, q_end in (r[:5] for r in rows):
        print(f"| {label}{'' if ok else ' (failed)'} | " + " | ".join(f"{a:.1e}" for a in at)
              + f" | {slope:.2f} | {q_end:.17g} |")
    if batch > 1:
        print(f"\n{batch} initial states of the same energy (phases 0 .. pi/2): median "
              "(largest) over the states\n")
        print(f"| GL nodes | GL weights | Lobatto points | {header} | median growth exponent |")
        print("|---|---|---|" + "---|" * (len(decades) + 1))
        for label, ok, *_, med, top, slope in rows:
            print(f"| {label}{'' if ok else ' (failed)'} | "
                  + " | ".join(f"{m:.1e} ({t:.1e})" for m, t in zip(med, top, strict=True))
                  + f" | {slope:.2f} |")
    print()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--batch", type=int, default=16, help="initial states (default 16)")
    parser.add_argument("--degree", type=int, default=7, help="CGVI degree (default 7)")
    parser.add_argument("--only", choices=("coefficients", "energy"))
    args = parser.parse_args(argv)
    if args.only != "energy":
        coefficient_table()
    if args.only != "coefficients":
        energy_growth(args.steps, args.batch, args.degree)


if __name__ == "__main__":
    main()
