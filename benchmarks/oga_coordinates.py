"""The OGA seed of a D-coordinate step: `fit_network` (one greedy fit per coordinate in a
compiled loop, `lax.map`) against the same fits under `vmap`, side by side. Width 10 tanh
network, the solver's default dictionary (`dict_amount=4000`, biases in (-π, π)), a smooth
target on the 33-point Simpson grid, float64. Prints the first call (trace + compile + run)
and the median of `--repeats` runs after it, per D. The first D's loop call also builds
the dictionary, which is cached for every call after it.

    .venv/bin/python -m benchmarks.oga_coordinates [--dims 1 2 4 8 16]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi.oga import fit_network, oga_fit  # noqa: E402
from diffrax_vi.parameter_seed import fit_problem  # noqa: E402

INTERVAL = (-math.pi, math.pi)


def vmapped_fit(basis, config, problem, dict_amount):
    """The per-coordinate fits of `fit_network`, batched with `vmap` (the former layout)."""
    def one(y):
        res = oga_fit(config, basis.activation, problem.nodes, problem.weights, y, basis.width,
                      bias_interval=INTERVAL, dict_amount=dict_amount,
                      modulation=problem.modulation, symmetry=basis.symmetry)
        return basis.from_neurons(res.W, res.b, res.c)

    return jax.vmap(one, in_axes=1, out_axes=1)(problem.targets)


def time_fit(fit, targets, repeats):
    start = time.perf_counter()
    jax.block_until_ready(fit(targets))
    first = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fit(targets))
        runs.append(time.perf_counter() - start)
    return first, statistics.median(runs), out


def compare(dims: int, repeats: int = 20, dict_amount: int = 4000):
    """(first-call s, run ms) of the compiled loop and of `vmap`, and their largest
    parameter difference, for `dims` coordinates."""
    basis = dvi.ShallowNetBasis(dvi.tanh, 10)
    tau = np.linspace(0, 1, 33)
    y = np.stack([np.sin(0.3 * (k + 1) * tau) for k in range(dims)], axis=1)
    problem = fit_problem(jnp.asarray(y), False, basis.zeros(dims, jnp.float64), jnp.array(True))
    config = dvi.OGA1d(bias_interval=INTERVAL, dict_amount=dict_amount)
    looped = jax.jit(lambda t: fit_network(basis, config, problem._replace(targets=t)))
    batched = jax.jit(lambda t: vmapped_fit(basis, config, problem._replace(targets=t),
                                            dict_amount))
    f_loop, r_loop, a = time_fit(looped, problem.targets, repeats)
    f_vmap, r_vmap, b = time_fit(batched, problem.targets, repeats)
    diff = float(jnp.max(jnp.abs(a - b)))
    return dict(loop=(f_loop, 1e3 * r_loop), vmap=(f_vmap, 1e3 * r_vmap), diff=diff)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dims", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--repeats", type=int, default=20)
    ns = parser.parse_args(argv)
    print("| coordinates | lax.map first call s | lax.map run ms | vmap first call s "
          "| vmap run ms | run ratio map/vmap | max parameter difference |")
    print("|---|---|---|---|---|---|---|")
    for d in ns.dims:
        r = compare(d, ns.repeats)
        print(f"| {d} | {r['loop'][0]:.2f} | {r['loop'][1]:.2f} | {r['vmap'][0]:.2f} | "
              f"{r['vmap'][1]:.2f} | {r['loop'][1] / r['vmap'][1]:.2f} | {r['diff']:.1e} |")


if __name__ == "__main__":
    main()
