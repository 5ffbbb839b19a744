"""Quickstart: a network variational integrator next to Tsit5, on two problems.

Integrates the harmonic oscillator (10 steps of h = 0.1) and the double pendulum (10 steps of
h = 0.1) with `NetworkVI` (ShallowNet ansatz, tanh, width 10) and with diffrax's `Tsit5` on the
same `LagrangianTerm`, prints the error against each problem's reference and the energy error,
then integrates the oscillator to t = 200 to show the bounded energy error of the variational
step against the drift of Tsit5 with the same fixed step, and saves a plot.

Run with `make demo` (or `python examples/quickstart.py [--out quickstart.png]`).
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402


def solve(problem, solver, ts, **kwargs):
    """Integrate `problem` on its grid with a fixed step; return `(q, p)` at `ts` and the time."""

    @eqx.filter_jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term,
            solver,
            problem.t0,
            float(ts[-1]),
            problem.dt,
            y0,
            args=problem.args,
            saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
            max_steps=len(ts) + 1,
            **kwargs,
        )

    start = time.perf_counter()
    sol = run(problem.y0)
    jax.block_until_ready(sol.ys)
    elapsed = time.perf_counter() - start
    return np.asarray(sol.ys[0]), np.asarray(sol.ys[1]), elapsed


def relative_energy_error(problem, q, p):
    energy = jax.vmap(lambda qq, pp: problem.energy(0.0, qq, pp))(jnp.asarray(q), jnp.asarray(p))
    energy = np.asarray(energy)
    return np.max(np.abs(energy - energy[0])) / abs(energy[0])


def compare(name, problem, network):
    ts = np.asarray(problem.ts)
    q_ref, _ = problem.reference(ts)
    rows = []
    for label, solver in (("NetworkVI", network), ("Tsit5", diffrax.Tsit5())):
        q, p, elapsed = solve(problem, solver, ts)
        err = np.max(np.abs(q - q_ref)) / np.max(np.abs(q_ref))
        rows.append((label, err, relative_energy_error(problem, q, p), elapsed))
    print(f"\n{name}: {len(ts) - 1} steps of h = {problem.dt}")
    print(f"  {'solver':10s} {'max rel. error of q':>20s} {'max rel. energy error':>22s}")
    for label, err, energy_err, _ in rows:
        print(f"  {label:10s} {err:20.2e} {energy_err:22.2e}")


def long_run(out: str | None):
    problem = problems.harmonic_oscillator(t1=200.0, dt=0.5)
    ts = np.asarray(problem.ts)
    network = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))
    curves = {}
    for label, solver in (("NetworkVI", network), ("Tsit5 (same fixed step)", diffrax.Tsit5())):
        q, p, _ = solve(problem, solver, ts)
        energy = np.asarray(jax.vmap(lambda a, b: problem.energy(0.0, a, b))(q, p))
        curves[label] = np.abs(energy - energy[0]) / abs(energy[0])
    print(f"\nHarmonic oscillator to t = {ts[-1]:g} with h = {problem.dt} ({len(ts) - 1} steps)")
    for label, err in curves.items():
        print(f"  {label:24s} energy error: first tenth {err[: len(err) // 10].max():.2e}, "
              f"last tenth {err[-len(err) // 10 :].max():.2e}")
    if out:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4))
        for label, err in curves.items():
            ax.semilogy(ts[1:], np.maximum(err[1:], 1e-17), label=label)
        ax.set_xlabel("t")
        ax.set_ylabel("relative energy error")
        ax.set_title(f"Harmonic oscillator, h = {problem.dt}")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out, dpi=120)
        print(f"\nplot written to {out}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="examples/quickstart.png", help="PNG path ('' for none)")
    args = parser.parse_args()

    network = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))
    compare("Harmonic oscillator", problems.harmonic_oscillator(), network)
    network16 = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(16))
    compare("Double pendulum", problems.double_pendulum(t1=1.0, dt=0.1), network16)
    long_run(args.out or None)


if __name__ == "__main__":
    main()
