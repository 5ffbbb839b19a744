"""Wall-clock time of one jitted `oga_fit` call (the per-step seed cost of the integrators).

Usage: `python benchmarks/oga_timing.py [--dtype float64] [--width 10] [--repeats 30]`.
Prints compile time and the median / minimum run time (after compilation) per dictionary size,
for a single target and for a batch of 8 targets under `vmap`.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from diffrax_vi.activations import relu_k, tanh  # noqa: E402
from diffrax_vi.oga import OGA1d, oga_fit  # noqa: E402
from diffrax_vi.quadrature import Simpson  # noqa: E402


def _time(fn, arg, repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(arg))
    compile_s = time.perf_counter() - start
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(arg))
        samples.append(time.perf_counter() - start)
    return compile_s, float(np.median(samples)), float(np.min(samples))


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dtype", default="float64")
    parser.add_argument("--width", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--activation", default="tanh", choices=["tanh", "relu3"])
    parser.add_argument("--sizes", default="400,4000,50000")
    args = parser.parse_args()

    dtype = jnp.dtype(args.dtype)
    activation = tanh if args.activation == "tanh" else relu_k(3)
    t_np, w_np = Simpson(10).nodes_weights_np()
    nodes = jnp.asarray(t_np, dtype)
    weights = jnp.asarray(w_np, dtype)
    y = jnp.asarray(np.cos(3 * t_np), dtype)
    ys = jnp.asarray(np.stack([np.cos((1 + 0.5 * k) * t_np) for k in range(8)]), dtype)
    print(
        f"jax {jax.__version__}, backend {jax.default_backend()}, dtype {dtype}, "
        f"activation {args.activation}, width {args.width}, M = {nodes.shape[0]}"
    )
    print(
        f"{'dict_amount':>11} {'atoms':>7} {'compile s':>10} {'median ms':>10} {'min ms':>8}"
        f" {'vmap8 median ms':>16}"
    )
    for amount in (int(s) for s in args.sizes.split(",")):

        def single(target, amount=amount):
            return oga_fit(
                OGA1d(), activation, nodes, weights, target, args.width, dict_amount=amount
            )

        fn = jax.jit(single)
        batched = jax.jit(jax.vmap(single))
        compile_s, median, minimum = _time(fn, y, args.repeats)
        _, bmedian, _ = _time(batched, ys, max(5, args.repeats // 3))
        print(
            f"{amount:>11} {2 * (amount + 1):>7} {compile_s:>10.2f} {1e3 * median:>10.3f}"
            f" {1e3 * minimum:>8.3f} {1e3 * bmedian:>16.3f}"
        )


if __name__ == "__main__":
    main()
