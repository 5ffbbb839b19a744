"""Kepler ensemble throughput on an accelerator: `vmap` of `CGVI(k)` with the Jacobian-free
engine (`ChordIteration(picard=True)`; and `Dopri8`) over N
orbits (e in [0.1, 0.6], 10 orbits each, float64), member-orbits per second and the largest
final position error against the exact solution.

    python -m benchmarks.gpu_kepler_ensemble [--members 1000 10000 100000] [--degree 6]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--members", type=int, nargs="+", default=[1000, 10000, 100000])
    parser.add_argument("--degree", type=int, default=6)
    parser.add_argument("--steps-per-orbit", type=int, default=64)
    parser.add_argument("--orbits", type=int, default=10)
    parser.add_argument("--dopri", action="store_true", help="also Dopri8 at rtol 1e-13")
    args = parser.parse_args()
    import diffrax
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import diffrax_vi as dvi
    from diffrax_vi.problems import kepler, solve_kepler_equation

    print(f"# jax {jax.__version__}, {jax.devices()[0].device_kind}", flush=True)
    term = kepler().term
    h = 2 * math.pi / args.steps_per_orbit
    n = args.steps_per_orbit * args.orbits
    t1 = n * h
    engine = dvi.ChordIteration(ftol=0.0, predict=True, picard=True)
    solvers = {f"CGVI({args.degree}) h=2pi/{args.steps_per_orbit}": (
        dvi.CGVI(args.degree, root_finder=engine), h, None)}
    if args.dopri:
        solvers["Dopri8 rtol 1e-13"] = (diffrax.Dopri8(), None,
                                        diffrax.PIDController(rtol=1e-13, atol=1e-13))
    for name, (solver, dt0, controller) in solvers.items():
        def one(q, p, solver=solver, dt0=dt0, controller=controller):
            sol = diffrax.diffeqsolve(
                term, solver, 0.0, t1, dt0, (q, p), max_steps=4 * n + 64,
                saveat=diffrax.SaveAt(t1=True),
                stepsize_controller=controller or diffrax.ConstantStepSize(),
            )
            return sol.ys[0][-1], sol.result

        run = jax.jit(jax.vmap(one))
        for members in args.members:
            e = np.linspace(0.1, 0.6, members)
            q = jnp.asarray(np.stack([1 - e, 0 * e], -1))
            p = jnp.asarray(np.stack([0 * e, np.sqrt((1 + e) / (1 - e))], -1))
            start = time.perf_counter()
            out, result = jax.block_until_ready(run(q, p))
            first = time.perf_counter() - start
            best = math.inf
            for _ in range(3):
                start = time.perf_counter()
                out, result = jax.block_until_ready(run(q, p))
                best = min(best, time.perf_counter() - start)
            exact = np.empty((members, 2))
            for i, ei in enumerate(e):
                anomaly = solve_kepler_equation(np.array([t1]), ei)[0]
                exact[i] = (math.cos(anomaly) - ei, math.sqrt(1 - ei * ei) * math.sin(anomaly))
            error = float(np.max(np.abs(np.asarray(out) - exact)))
            ok = int(np.sum(np.asarray(result == diffrax.RESULTS.successful)))
            print(f"{name:28s} N={members:7d}: {members * args.orbits / best:12.0f} "
                  f"member-orbits/s ({best:.3f} s; first call {first:.1f} s), max error "
                  f"{error:.1e}, {ok}/{members} successful", flush=True)


if __name__ == "__main__":
    main()
