"""Why long NetworkVI runs of the reference's pendulum fail: the p₂ = 0 constraint.

The reference's pendulum is the degenerate two-component form `q = (θ, ω)` whose Lagrangian
is linear in the velocity, so the second momentum is constrained: `p₂ = ∂L/∂v₂ = 0` on every
exact solution. A network step that is not exact leaves a small `p₂ ≠ 0`; the next step's
equations then have no exact root, and the error grows step by step until a solve stalls.

This script measures that, one compiled `lax.scan` of `NetworkVI.step` per run:

1. `p₂` and the error of `θ` after one step of h, for NetworkVI (tanh, width `--width` and
   12, R = 8 Gauss–Legendre nodes) and `CGVI(7)`;
2. a run of `--steps` steps: `p₂` and the step's final residual at a few steps, and the
   first failed step;
3. the same run with `p₂ := 0` after every step, and with also `p₁ := m l² ω` (projections
   onto the constraint; not part of the variational map, and not offered by the solver):
   steps done and largest relative energy error.

    .venv/bin/python -m benchmarks.pendulum_constraint [--steps 2000] [--h 0.1]
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402


def network(width: int) -> dvi.NetworkVI:
    return dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(8),
                         formulation=dvi.FreeEndpoints())


def run_steps(solver, problem, h: float, steps: int, projection: str = "none"):
    """`steps` steps of `solver` from the problem's start, as one compiled scan; after each
    step `projection` sets `p₂ := 0` ("p2") or also `p₁ := m l² ω` ("both"). Returns the
    per-step (q, p, success, final residual), stopping where a step fails (later entries
    NaN)."""
    term, args = problem.term, problem.args
    ml2 = float(problem.term.momentum(0.0, jnp.array([0.0, 1.0]), jnp.zeros(2), args)[0])

    @eqx.filter_jit
    def scan(y0):
        state = solver.init(term, 0.0, h, y0, args)

        def body(carry, n):
            y, state, alive = carry
            t0 = n * h
            y1, _, _, state1, result = solver.step(term, t0, t0 + h, y, args, state, False)
            ok = alive & (result == diffrax.RESULTS.successful)
            q1, p1 = y1
            if projection in ("p2", "both"):
                p1 = p1.at[1].set(0.0)
            if projection == "both":
                p1 = p1.at[0].set(ml2 * q1[1])
            y1 = (q1, p1)
            nan = jnp.full_like(q1, jnp.nan)
            out = (jnp.where(ok, q1, nan), jnp.where(ok, p1, nan), ok, state1.report.residual)
            y_next = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), y1, y)
            return (y_next, state1, ok), out

        _, outs = jax.lax.scan(body, (y0, state, jnp.array(True)), jnp.arange(steps))
        return outs

    q, p, ok, residual = (np.asarray(a) for a in scan(problem.y0))
    return q, p, ok, residual


def first_failure(ok: np.ndarray) -> int | None:
    bad = np.flatnonzero(~ok)
    return int(bad[0]) + 1 if bad.size else None


def energy_error(problem, q, p, ok) -> float:
    e0 = float(problem.energy(problem.t0, *problem.y0))
    energy = jax.vmap(lambda a, b: problem.energy(0.0, a, b))
    energies = np.asarray(energy(jnp.asarray(q[ok]), jnp.asarray(p[ok])))
    return float(np.max(np.abs(energies - e0)) / abs(e0)) if energies.size else float("nan")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--h", type=float, default=0.1)
    parser.add_argument("--width", type=int, default=8)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--probe", type=int, nargs="*", default=[1, 42, 102],
                        help="steps at which to print p₂ and the residual")
    ns = parser.parse_args(argv)
    h = ns.h
    problem = problems.pendulum(dtype=jnp.float64)

    print(f"1. one step of h = {h} from θ₀ = {float(problem.y0[0][0]):.6f}, ω₀ = 0:")
    theta_ref = float(problem.reference(np.array([h]))[0][0][0])
    for name, solver in ((f"NetworkVI tanh{ns.width} R8", network(ns.width)),
                         ("NetworkVI tanh12 R8", network(12)), ("CGVI(7)", dvi.CGVI(7))):
        q, p, ok, _ = run_steps(solver, problem, h, 1)
        print(f"   {name:22s} p₂ = {p[0, 1]: .2e}, θ error = {q[0, 0] - theta_ref: .2e}"
              f"{'' if ok[0] else ' (step failed)'}")

    solver = network(ns.width)
    print(f"2. {ns.steps} steps, NetworkVI tanh{ns.width} R8, no projection:")
    q, p, ok, residual = run_steps(solver, problem, h, ns.steps)
    for n in ns.probe:
        if n <= ns.steps and ok[n - 1]:
            print(f"   step {n:5d}: p₂ = {p[n - 1, 1]: .2e}, final residual {residual[n - 1]:.1e}")
    fail = first_failure(ok)
    if fail is None:
        print("   no step failed")
    else:
        last = f", p₂ before it {p[fail - 2, 1]: .2e}" if fail > 1 else ""
        print(f"   first failed step: {fail} (residual {residual[fail - 1]:.1e}{last})")

    print("3. with a projection after every step:")
    for projection, label in (("p2", "p₂ := 0"), ("both", "p₂ := 0, p₁ := m l² ω")):
        q, p, ok, _ = run_steps(solver, problem, h, ns.steps, projection)
        fail = first_failure(ok)
        done = ns.steps if fail is None else fail - 1
        print(f"   {label:22s} steps done {done} of {ns.steps}, largest relative energy "
              f"error {energy_error(problem, q, p, ok):.2e}")


if __name__ == "__main__":
    main()
