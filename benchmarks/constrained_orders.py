"""The constrained step's claims, measured: order against the angle-coordinate references,
drift and energy over 10^5 steps, and the gradient with respect to the chain's damping
against finite differences (float64).

    .venv/bin/python -m benchmarks.constrained_orders [--long-steps 100000]
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--long-steps", type=int, default=100_000)
    args = parser.parse_args()
    import diffrax
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import diffrax_vi as dvi
    from diffrax_vi import problems

    t1 = 2.0
    print(f"# order at T = {t1} against the angle-coordinate references (max-norm of q, p)")
    for problem in (problems.spherical_pendulum(), problems.rigid_chain()):
        q_ref, p_ref = problem.reference(np.array([t1]))
        for degree in (2, 3, 4):
            errors = []
            for n in (20, 40, 80):
                sol = diffrax.diffeqsolve(problem.term, dvi.CGVI(degree), 0.0, t1, t1 / n,
                                          problem.y0, max_steps=n + 8)
                errors.append(max(np.max(np.abs(np.asarray(sol.ys[0][-1]) - q_ref[0])),
                                  np.max(np.abs(np.asarray(sol.ys[1][-1]) - p_ref[0]))))
            orders = [np.log2(a / b) for a, b in zip(errors, errors[1:], strict=False)]
            print(f"{problem.name:20s} CGVI({degree})  errors " +
                  " / ".join(f"{e:.2e}" for e in errors) +
                  "  orders " + ", ".join(f"{o:.2f}" for o in orders))

    problem = problems.spherical_pendulum()
    n, dt = args.long_steps, 0.05
    ts = jnp.linspace(0.0, n * dt, 1001)
    sol = diffrax.diffeqsolve(problem.term, dvi.CGVI(2), 0.0, n * dt, dt, problem.y0,
                              saveat=diffrax.SaveAt(ts=ts, solver_state=True), max_steps=n + 8)
    energy = np.asarray(jax.vmap(problem.energy)(ts, *sol.ys))
    error = np.abs(energy - energy[0])
    drift = np.asarray(sol.solver_state.holonomic_drift)
    print(f"# spherical pendulum, CGVI(2), dt = {dt}, {n} steps: drift |g| = {drift[0]:.1e}, "
          f"|G v| = {drift[1]:.1e}; energy error max {error.max():.4e}, first tenth "
          f"{error[:101].max():.4e}")

    chain = problems.rigid_chain(n_links=5, damping=0.05)

    def end_height(c):
        term = eqx.tree_at(lambda t: t.nonconservative_force.damping, chain.term, c)
        sol = diffrax.diffeqsolve(term, dvi.CGVI(2), 0.0, 1.0, 0.05, chain.y0, max_steps=32)
        return sol.ys[0][-1, -1]

    c = jnp.asarray(0.05)
    grad = float(jax.grad(end_height)(c))
    value = jax.jit(end_height)
    fd = (float(value(c + 1e-5)) - float(value(c - 1e-5))) / 2e-5
    print(f"# chain: d(end height)/d(damping) = {grad:.12e}, finite differences {fd:.12e}, "
          f"difference {abs(grad - fd):.1e}")


if __name__ == "__main__":
    main()
