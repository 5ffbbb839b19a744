"""The accuracy figures quoted for the integrator families, from one command.

Prints, in float64: the one-step-forward-and-back distance of the reversible variants (and of
plain ShallowNet) on the harmonic oscillator and the double pendulum; the error of the
shared-weight reversible variant at two step sizes (its order); cGVI convergence slopes; the
damped time-dependent oscillator with each initial trajectory; and PIDController against
constant steps on Kepler (e = 0.6, one period).

    .venv/bin/python benchmarks/family_figures.py
"""

from __future__ import annotations

import math

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402

B, GL = dvi.ShallowNetBasis, dvi.GaussLegendre


def end_error(problem, sol):
    q_ref, p_ref = problem.reference(np.asarray(sol.ts)[-1:])
    return max(
        float(np.max(np.abs(np.asarray(sol.ys[0])[-1] - q_ref[0]))),
        float(np.max(np.abs(np.asarray(sol.ys[1])[-1] - p_ref[0]))),
    )


def roundtrip(problem, solver, h=0.1):
    def one(y, t0, t1):
        sol = diffrax.diffeqsolve(problem.term, solver, t0, t1, t1 - t0, y, args=problem.args)
        return sol.ys[0][-1], sol.ys[1][-1]

    y2 = one(one(problem.y0, 0.0, h), h, 0.0)
    return max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(y2, problem.y0, strict=True))


def main():
    print("one step forward and back, max |y - y0|")
    for name, make in [
        ("ShallowNet", dvi.ShallowNet),
        ("ShallowNetReversible", dvi.ShallowNetReversible),
        ("ShallowNetAutodiffReversible", dvi.ShallowNetAutodiffReversible),
    ]:
        ho = roundtrip(problems.harmonic_oscillator(), make(B(dvi.tanh, 10), GL(8)))
        dp = roundtrip(problems.double_pendulum(), make(B(dvi.tanh, 10), GL(16)))
        print(f"  {name:30s} HO {ho:.2e}  double pendulum {dp:.2e}")

    print("shared output weights (interpolating, gelu width 8): error by step size")
    errs = []
    for dt in (0.2, 0.1):
        problem = problems.harmonic_oscillator(dt=dt)
        solver = dvi.ShallowNetAutodiffReversible(B(dvi.gelu, 8), GL(8), shared_output_weights=True)
        sol = diffrax.diffeqsolve(
            problem.term, solver, problem.t0, problem.t1, problem.dt, problem.y0, args=problem.args
        )
        errs.append(end_error(problem, sol))
    print(f"  h=0.2 {errs[0]:.2e}  h=0.1 {errs[1]:.2e}  order {math.log2(errs[0] / errs[1]):.2f}")

    print("CGVI(s), GL(s+1), HO to t = 4: slopes for h = 0.4, 0.2, 0.1")
    for degree in (1, 2, 3):
        hs, errs = (0.4, 0.2, 0.1), []
        for h in hs:
            problem = problems.harmonic_oscillator(t1=4.0, dt=h)
            sol = diffrax.diffeqsolve(
                problem.term, dvi.CGVI(degree), 0.0, 4.0, h, problem.y0, args=problem.args
            )
            errs.append(end_error(problem, sol))
        slopes = np.diff(np.log(errs)) / np.diff(np.log(hs))
        print(f"  degree {degree}: errors {', '.join(f'{e:.2e}' for e in errs)}; slopes {slopes}")

    print("damped oscillator e^(0.2 t)(v²/2 − q²/2) from t0 = 1, 10 steps of 0.1: max error")
    gamma, t0, q0, v0 = 0.2, 1.0, 0.5, -0.3
    term = dvi.LagrangianTerm(
        lambda t, q, v, args: jnp.exp(gamma * t) * (0.5 * v @ v - 0.5 * q @ q)
    )
    w = math.sqrt(1 - gamma**2 / 4)
    c, s = math.cos(w * t0), math.sin(w * t0)
    m = math.exp(-gamma * t0 / 2) * np.array(
        [[c, s], [-gamma / 2 * c - w * s, -gamma / 2 * s + w * c]]
    )
    a, b = np.linalg.solve(m, [q0, v0])
    ts = np.linspace(t0, t0 + 1, 11)
    exact = np.exp(-gamma * ts / 2) * (a * np.cos(w * ts) + b * np.sin(w * ts))
    y0 = (jnp.array([q0]), jnp.array([math.exp(gamma * t0) * v0]))
    for method in (dvi.ShallowNet, dvi.ShallowNetAutodiff):
        for traj in (dvi.IntegratorExtrapolation(), dvi.HermiteExtrapolation(),
                     dvi.NoExtrapolation(), dvi.PreviousStep()):  # fmt: skip
            try:
                solver = method(B(dvi.tanh, 10), GL(8), initial_trajectory_method=traj)
            except ValueError:
                continue
            sol = diffrax.diffeqsolve(
                term, solver, t0, t0 + 1, 0.1, y0, saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
                throw=False,
            )  # fmt: skip
            ok = sol.result == diffrax.RESULTS.successful
            err = np.max(np.abs(np.asarray(sol.ys[0][:, 0]) - exact)) if ok else float("nan")
            status = "ok" if ok else "failed"
            print(f"  {method.__name__:20s} {type(traj).__name__:24s} {status} {err:.2e}")

    print("Kepler e = 0.6, one period")
    problem = problems.kepler(eccentricity=0.6, t1=2 * math.pi)
    t1 = 2 * math.pi
    sol = diffrax.diffeqsolve(
        problem.term, dvi.NetworkVI(B(dvi.tanh, 10), GL(8), error_estimate=3), 0.0, t1, 0.1,
        problem.y0, args=problem.args, saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
    )  # fmt: skip
    accepted, rejected = int(sol.stats["num_accepted_steps"]), int(sol.stats["num_rejected_steps"])
    print(
        f"  PID rtol=atol=1e-6: {accepted} accepted + {rejected} rejected steps, "
        f"error {end_error(problem, sol):.2e}"
    )
    for n in (32, 64):
        sol = diffrax.diffeqsolve(
            problem.term, dvi.NetworkVI(B(dvi.tanh, 10), GL(8)), 0.0, t1, t1 / n, problem.y0,
            args=problem.args, saveat=diffrax.SaveAt(t1=True),
        )  # fmt: skip
        print(f"  constant {n} steps: error {end_error(problem, sol):.2e}")


if __name__ == "__main__":
    main()
