"""Time of one Newton Jacobian of a NetworkVI step: forward-mode differentiation of the whole
residual (`jax.jacfwd`, the default) against the block assembly of `FreeEndpoints.jacobian`
(`LevenbergMarquardt(jacobian="structured")`), per problem, and their largest difference.

Each is timed as 100 evaluations inside one compiled `lax.scan` (median of `--repeats` runs),
at random parameters of a ShallowNet tanh network, float64.

    .venv/bin/python -m benchmarks.jacobian [--repeats 5] [--problems ...]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402

# problem -> (network width S, Gauss-Legendre nodes R): the reference benchmark's settings
FIXTURES = {
    "harmonic_oscillator": (10, 8),
    "double_pendulum": (10, 16),
    "kepler": (10, 8),
    "toda_lattice": (8, 16),
}
CALLS = 100


def _timed(fn, x, repeats):
    jax.block_until_ready(fn(x))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - start)
    return float(np.median(times)) / CALLS


def measure(name: str, repeats: int) -> dict:
    width, nodes = FIXTURES[name]
    problem = getattr(problems, name)(dtype=jnp.float64)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(nodes),
                           formulation=dvi.FreeEndpoints())
    ctx = solver.step_context(problem.term, 0.0, 0.1, problem.y0, problem.args)
    dim = ctx.q0.shape[0]
    theta = 0.5 * jax.random.normal(jax.random.PRNGKey(0), (solver.basis.num_params(), dim))
    flat, unravel = ravel_pytree((theta, ctx.p0 + 0.1))
    form = solver.formulation

    def dense(v):
        return jax.jacfwd(lambda u: ravel_pytree(form.residual(unravel(u), ctx))[0])(v)

    def blocks(v):
        return form.jacobian(unravel(v), ctx)

    def in_scan(jac):
        def body(v, _):
            return v + 1e-12 * jac(v)[0], None

        return jax.jit(lambda v: jax.lax.scan(body, v, None, length=CALLS)[0])

    a, b = jax.jit(dense)(flat), jax.jit(blocks)(flat)
    return dict(
        problem=name, unknowns=flat.size,
        jacfwd_ms=1e3 * _timed(in_scan(dense), flat, repeats),
        structured_ms=1e3 * _timed(in_scan(blocks), flat, repeats),
        difference=float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(a))),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--problems", nargs="*", default=list(FIXTURES))
    args = parser.parse_args()
    print("| problem | unknowns | jacfwd ms | structured ms | ratio | max rel. difference |")
    print("|---|---|---|---|---|---|")
    for name in args.problems:
        r = measure(name, args.repeats)
        print(f"| {r['problem']} | {r['unknowns']} | {r['jacfwd_ms']:.3f} | "
              f"{r['structured_ms']:.3f} | {r['jacfwd_ms'] / r['structured_ms']:.1f} | "
              f"{r['difference']:.1e} |", flush=True)


if __name__ == "__main__":
    main()
