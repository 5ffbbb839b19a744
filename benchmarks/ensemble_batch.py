"""Time per member of `dvi.ensemble` over oscillator solves for several `batch_size` values.

Members: 10 steps of h = 0.1 of the harmonic oscillator from random amplitudes (seeded),
`NetworkVI(ShallowNetBasis(tanh, 10), GaussLegendre(8))` with its default (projected) step, or
with `--all-parameter` the `FreeEndpoints()` step, or with `--cgvi 7` the polynomial `CGVI(7)`.
Median of `--repeats` runs after compiling.

    taskset -c 1 .venv/bin/python -m benchmarks.ensemble_batch --members 512
    taskset -c 1 .venv/bin/python -m benchmarks.ensemble_batch \\
        --all-parameter --members 64 --repeats 3
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--members", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--all-parameter", action="store_true")
    parser.add_argument("--cgvi", type=int, default=None, metavar="DEGREE")
    parser.add_argument("--batch-sizes", nargs="+", default=["None", "1", "16", "64"])
    args = parser.parse_args(argv)
    ho = problems.harmonic_oscillator()
    options = dict(formulation=dvi.FreeEndpoints()) if args.all_parameter else {}
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8), **options)
    if args.cgvi is not None:
        solver = dvi.CGVI(args.cgvi)

    def member(y0):
        sol = diffrax.diffeqsolve(ho.term, solver, 0.0, 1.0, 0.1, y0,
                                  saveat=diffrax.SaveAt(t1=True))
        return sol.ys[0][-1]

    rng = np.random.default_rng(0)
    q = jnp.asarray(rng.uniform(0.1, 1.0, (args.members, 1)))
    y0 = (q, jnp.zeros_like(q))
    step = "all-parameter" if args.all_parameter else "default (projected)"
    if args.cgvi is not None:
        step = f"CGVI({args.cgvi})"
    print(f"{step} step, {args.members} members, median of {args.repeats} runs")
    for text in args.batch_sizes:
        size = None if text == "None" else int(text)

        def run(y, size=size):
            return dvi.ensemble(member, y, batch_size=size)

        jax.block_until_ready(run(y0))
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(run(y0))
            times.append(time.perf_counter() - start)
        print(f"batch_size={text}: {1e6 * statistics.median(times) / args.members:.1f} us/member")


if __name__ == "__main__":
    main()
