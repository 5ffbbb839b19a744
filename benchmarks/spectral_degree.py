"""Spectral CGVI (issue 28): one-step error against the polynomial degree at large steps,
next to the two error models of `diffrax_vi.spectral`, and the degrees they choose.

1. Oscillator, ω = 1, steps h = 1, 2, π: the largest one-step error from the unit states
   (1, 0) and (0, 1) for degrees 1..14, the `"oscillator"` estimate (exact for this problem:
   the measured value lies between it/√2 and it) and the `"analytic"` estimate.
2. Kepler, e = 0.5, h = 2π/16 and 2π/8, time scale the pericentre passage
   `r_p/|v_p| = (1 − e)^1.5 / √(1 + e)`: the largest one-step error relative to the state
   over 32 starts along the orbit (exact reference), for even degrees 2..16, with both
   estimates.
3. The degrees each model chooses for several tolerances, and the measured one-step error
   at the chosen degree.
4. Quadrature: Kepler at h = 2π/8, `CGVI(s)` with Gauss–Legendre of s + 1, s + 2 and 2s nodes.
5. The reference pendulum (a degenerate Lagrangian, `IODETerm`) against the same pendulum
   as a regular Lagrangian `L = v²/2 + cos q` (reference: scipy DOP853, rtol 1e-13), h = 2,
   amplitude 1.98 rad about the stable point: the error falls about half as fast in the
   degree for the degenerate form.

    taskset -c 0 .venv/bin/python -m benchmarks.spectral_degree \\
        > benchmarks/results/spectral_degree.txt
"""

from __future__ import annotations

import math
import sys

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.spectral import spectral_degree, spectral_step_error  # noqa: E402


def one_step(term, solver, h, q0, p0, args=None):
    """One step of `h[i]` from each start `(q0[i], p0[i])`, one compiled vmapped solve."""
    def step(h, q, p):
        sol = diffrax.diffeqsolve(term, solver, 0.0, h, h, (q, p), args=args, max_steps=2,
                                  throw=False)
        return sol.ys[0][-1], sol.ys[1][-1]

    h = jnp.broadcast_to(jnp.asarray(h, jnp.float64), (len(q0),))
    q, p = jax.jit(jax.vmap(step))(h, jnp.asarray(q0), jnp.asarray(p0))
    return np.asarray(q), np.asarray(p)


def relative_errors(q, p, q0, p0, q1, p1):
    y0, y1 = np.concatenate([q0, p0], 1), np.concatenate([q1, p1], 1)
    return np.linalg.norm(np.concatenate([q, p], 1) - y1, axis=1) / np.linalg.norm(y0, axis=1)


def oscillator(steps, degrees):
    table = {}
    for s in degrees:
        table.update(oscillator_single(steps, s))
        print(f"oscillator degree {s} done", file=sys.stderr, flush=True)
    print("## 1. Oscillator, omega = 1: one-step error (measured / oscillator estimate / "
          "analytic estimate)\n")
    print("| degree | " + " | ".join(f"h = {h:.4g}" for h in steps) + " |")
    print("|---|" + "---|" * len(steps))
    for s in degrees:
        cells = [f"{table[s][i]:.1e} / {spectral_step_error(s, h, 1.0, 'oscillator'):.1e} / "
                 f"{spectral_step_error(s, h, 1.0):.1e}" for i, h in enumerate(steps)]
        print(f"| {s} | " + " | ".join(cells) + " |")
    print()
    return table


def kepler_errors(e, steps, degrees, quadrature=lambda s: s + 1):
    problem = problems.kepler(e)
    starts = np.linspace(0.0, 2 * math.pi, 32, endpoint=False)
    q0, p0 = problem.reference(np.tile(starts, len(steps)))
    h = np.repeat(steps, len(starts))
    q1, p1 = problem.reference(np.tile(starts, len(steps)) + h)
    table = {}
    for s in degrees:
        solver = dvi.CGVI(s, dvi.GaussLegendre(quadrature(s)))
        q, p = one_step(problem.term, solver, h, q0, p0)
        err = relative_errors(q, p, q0, p0, q1, p1).reshape(len(steps), len(starts))
        table[s] = np.where(np.isfinite(err), err, np.inf).max(axis=1)
        print(f"kepler degree {s} done", file=sys.stderr, flush=True)
    return table


def main() -> None:
    steps = (1.0, 2.0, math.pi)
    osc = oscillator(steps, range(1, 15))

    e = 0.5
    tau = (1 - e) ** 1.5 / math.sqrt(1 + e)
    ksteps = (2 * math.pi / 16, 2 * math.pi / 8)
    kdeg = range(2, 17, 2)
    kep = kepler_errors(e, ksteps, kdeg)
    print(f"## 2. Kepler, e = {e}, time scale r_p/|v_p| = {tau:.4f}: largest one-step error "
          "over 32 starts (measured / analytic estimate / oscillator estimate)\n")
    print("| degree | " + " | ".join(f"h = 2pi/{round(2 * math.pi / h)}" for h in ksteps) + " |")
    print("|---|" + "---|" * len(ksteps))
    for s in kdeg:
        cells = [f"{kep[s][i]:.1e} / {spectral_step_error(s, h, tau):.1e} / "
                 f"{spectral_step_error(s, h, tau, 'oscillator'):.1e}"
                 for i, h in enumerate(ksteps)]
        print(f"| {s} | " + " | ".join(cells) + " |")
    print()

    print("## 3. Chosen degrees (analytic / oscillator model) and the measured one-step error "
          "at the chosen degree\n")
    print("| problem | h | rtol | analytic: degree, measured | oscillator: degree, measured |")
    print("|---|---|---|---|---|")
    cases = [("oscillator", h, 1.0, rtol, osc, steps) for h in steps for rtol in (1e-6, 1e-10)]
    cases += [("Kepler e=0.5", h, tau, rtol, kep, ksteps) for h in ksteps for rtol in (1e-6,)]
    for name, h, scale, rtol, table, hs in cases:
        cells = []
        for model in ("analytic", "oscillator"):
            s = spectral_degree(h, scale, rtol, model=model)
            if s not in table:  # measure the chosen degree if the tables lack it
                extra = (kepler_errors(e, hs, [s]) if name.startswith("Kepler")
                         else oscillator_single(hs, s))
                table[s] = extra[s]
            measured = table[s][hs.index(h)]
            cells.append(f"{s}, {measured:.1e}{'' if measured <= rtol else ' (MISSED)'}")
        print(f"| {name} | {h:.4g} | {rtol:g} | " + " | ".join(cells) + " |")
    print()

    quad = {}
    rules = (("s+1", lambda s: s + 1), ("s+2", lambda s: s + 2), ("2s", lambda s: 2 * s))
    for label, rule in rules:
        quad[label] = kepler_errors(e, (2 * math.pi / 8,), (4, 8, 12), rule)
    print("## 4. Quadrature, Kepler e = 0.5, h = 2pi/8: largest one-step error\n")
    print("| degree | GL(s+1) | GL(s+2) | GL(2s) |")
    print("|---|---|---|---|")
    for s in (4, 8, 12):
        print(f"| {s} | " + " | ".join(f"{quad[k][s][0]:.2e}" for k in quad) + " |")
    print()

    pendulum(2.0, range(2, 11, 2))


def oscillator_single(steps, s):
    """`{s: one-step errors}` of `CGVI(s)` on the oscillator (ω = 1) at each of `steps`,
    from two starting phases."""
    problem = problems.harmonic_oscillator(k=1.0, q0=1.0)
    h = np.repeat(steps, 2)
    q0 = np.tile([[1.0], [0.0]], (len(steps), 1))
    p0 = np.tile([[0.0], [1.0]], (len(steps), 1))
    q1 = q0 * np.cos(h)[:, None] + p0 * np.sin(h)[:, None]
    p1 = p0 * np.cos(h)[:, None] - q0 * np.sin(h)[:, None]
    q, p = one_step(problem.term, dvi.CGVI(s), h, q0, p0)
    return {s: np.hypot(q - q1, p - p1)[:, 0].reshape(len(steps), 2).max(axis=1)}


def pendulum(h, degrees):
    from scipy.integrate import solve_ivp

    problem = problems.pendulum()
    amplitude = math.pi - math.acos(0.4)  # about the stable point θ = π
    period = 8.3
    starts = np.linspace(0.0, period, 32, endpoint=False)
    q0, p0 = problem.reference(starts)
    q1, p1 = problem.reference(starts + h)
    regular = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * jnp.sum(v**2) + jnp.sum(jnp.cos(q)))
    ivp = solve_ivp(lambda t, y: [y[1], -math.sin(y[0])], (0.0, period + h), [amplitude, 0.0],
                    method="DOP853", rtol=1e-13, atol=1e-15, dense_output=True)
    r0, r1 = ivp.sol(starts), ivp.sol(starts + h)
    print(f"## 5. Pendulum, amplitude {amplitude:.3f} rad, h = {h:g}: largest one-step error "
          "over 32 starts\n")
    print("| degree | degenerate (IODETerm, reference problem) | regular Lagrangian |")
    print("|---|---|---|")
    for s in degrees:
        q, p = one_step(problem.term, dvi.CGVI(s), h, q0, p0, problem.args)
        degenerate = relative_errors(q, p, q0, p0, q1, p1).max()
        q, p = one_step(regular, dvi.CGVI(s), h, r0[0][:, None], r0[1][:, None])
        reg = relative_errors(q, p, r0[0][:, None], r0[1][:, None], r1[0][:, None],
                              r1[1][:, None]).max()
        print(f"| {s} | {degenerate:.1e} | {reg:.1e} |", flush=True)
        print(f"pendulum degree {s} done", file=sys.stderr, flush=True)
    print()


if __name__ == "__main__":
    main()
