"""Per-step cost of the two derivative backends of the network ansätze, side by side.

The reference computes the ansatz derivatives by compiled symbolic kernels and measured them
18–62× faster than ForwardDiff. Here both backends end up as XLA code: `"autodiff"` (JAX
differentiates the network) and `"sympy"` (closed-form first derivatives from sympy, compiled
to JAX). This script runs the same solve with each and prints compile time, median time per
step over the repeats, their ratio, and the largest difference between the two solutions.

Problem: harmonic oscillator, float64, `--steps` steps of h = 0.1; ansätze: ShallowNet tanh
width 10 (GL8) and, when available, DenseNet tanh 8×8 (GL8).

    .venv/bin/python benchmarks/derivatives.py [--steps 200] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402


def measure(problem, solver, repeats):
    @eqx.filter_jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, problem.dt, y0,
            args=problem.args, throw=False, max_steps=problem.n_steps + 1,
        )  # fmt: skip

    start = time.perf_counter()
    sol = jax.block_until_ready(run(problem.y0))
    first = time.perf_counter() - start
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run(problem.y0))
        samples.append(time.perf_counter() - start)
    med = statistics.median(samples)
    return dict(
        sol=sol,
        compile_s=first - med,
        step_ms=1e3 * med / problem.n_steps,
        ok=bool(sol.result == diffrax.RESULTS.successful),
    )


def bases():
    yield "ShallowNet tanh 10", lambda d: dvi.ShallowNetBasis(dvi.tanh, 10, derivatives=d), None
    if hasattr(dvi, "DenseNetBasis"):
        yield (
            "DenseNet tanh 8x8",
            lambda d: dvi.DenseNetBasis(dvi.tanh, 8, 8, derivatives=d),
            dvi.LSGD(),
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    problem = problems.harmonic_oscillator(t1=0.1 * args.steps)
    print(f"harmonic oscillator, {args.steps} steps of h = 0.1, float64, {jax.devices()[0]}")
    print("| ansatz | backend | result | compile s | ms / step | sympy / autodiff | max diff |")
    print("|---|---|---|---|---|---|---|")
    for name, make, guess in bases():
        rows = {}
        for backend in ("autodiff", "sympy"):
            kwargs = {} if guess is None else dict(initial_guess=guess)
            solver = dvi.NetworkVI(make(backend), dvi.GaussLegendre(8),
                                   **{"formulation": dvi.FreeEndpoints(), **kwargs})
            rows[backend] = measure(problem, solver, args.repeats)
        diff = max(
            float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
            for a, b in zip(rows["sympy"]["sol"].ys, rows["autodiff"]["sol"].ys, strict=True)
        )
        ratio = rows["sympy"]["step_ms"] / rows["autodiff"]["step_ms"]
        for backend, r in rows.items():
            shown = f"{ratio:.2f}" if backend == "sympy" else ""
            print(
                f"| {name} | {backend} | {'ok' if r['ok'] else 'failed'} | {r['compile_s']:.1f} "
                f"| {r['step_ms']:.2f} | {shown} | {diff if backend == 'sympy' else '':.3g} |"
                if backend == "sympy"
                else f"| {name} | {backend} | {'ok' if r['ok'] else 'failed'} | "
                f"{r['compile_s']:.1f} | {r['step_ms']:.2f} | | |"
            )


if __name__ == "__main__":
    main()
