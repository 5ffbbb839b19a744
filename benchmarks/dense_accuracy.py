"""Accuracy of the dense output inside the steps and at the step ends (how-to: dense output).

The harmonic-oscillator fixture (`problems.harmonic_oscillator()`, q(t) = 0.5 cos(t/√2)),
tanh width 10, Gauss–Legendre 8, 10 steps of 0.1, float64, for free and interpolating
endpoints. `sol.evaluate` and `sol.derivative` are compared with the exact solution at the
points of a grid of 1001 times that are not step ends.

    .venv/bin/python -m benchmarks.dense_accuracy
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402


def main() -> None:
    problem = problems.harmonic_oscillator()
    omega = np.sqrt(0.5)
    basis = dvi.ShallowNetBasis(dvi.tanh, 10)
    solvers = {
        "default (projected step)": dvi.NetworkVI(basis, dvi.GaussLegendre(8)),
        "free endpoints (all-parameter)": dvi.NetworkVI(
            basis, dvi.GaussLegendre(8), formulation=dvi.FreeEndpoints()
        ),
        "interpolating endpoints": dvi.NetworkVI(
            basis,
            dvi.GaussLegendre(8),
            formulation=dvi.InterpolatingEndpoints(),
            seed=dvi.SeedPolicy(initial_guess=dvi.OGA1dNormalized()),
        ),
    }
    ts = np.linspace(0.0, 1.0, 1001)
    inner = ts[np.abs(ts * 10 - np.round(ts * 10)) > 1e-9]
    ends = np.linspace(0.0, 1.0, 11)
    evaluate = jax.jit(jax.vmap(lambda sol, t: sol.evaluate(t)[0][0], in_axes=(None, 0)))
    derivative = jax.jit(jax.vmap(lambda sol, t: sol.derivative(t)[0][0], in_axes=(None, 0)))
    for name, solver in solvers.items():
        sol = diffrax.diffeqsolve(
            problem.term, solver, 0.0, 1.0, 0.1, problem.y0,
            saveat=diffrax.SaveAt(ts=jnp.asarray(ends), dense=True),
        )
        q = np.asarray(evaluate(sol, jnp.asarray(inner)))
        dq = np.asarray(derivative(sol, jnp.asarray(inner)))
        error_q = np.abs(q - 0.5 * np.cos(omega * inner))
        error_dq = np.abs(dq + 0.5 * omega * np.sin(omega * inner))
        error_ends = np.abs(np.asarray(sol.ys[0][:, 0]) - 0.5 * np.cos(omega * ends))
        print(
            f"{name}: inside the steps q max {error_q.max():.1e} (median "
            f"{np.median(error_q):.1e}), dq/dt max {error_dq.max():.1e} (median "
            f"{np.median(error_dq):.1e}); at the step ends q max {error_ends.max():.1e}"
        )


if __name__ == "__main__":
    main()
