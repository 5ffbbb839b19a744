"""RATTLE compositions against the constrained Galerkin step, at equal error (issue 64).

Two constrained problems in Cartesian coordinates, with their multipliers:

- `problems.rigid_chain()`: 5 planar links, gravity, joint damping 0.05, T = 10;
- `problems.spherical_pendulum()`: a point on a sphere under gravity, T = 10.

Tools, each `jax.jit` around the whole `diffeqsolve(..., saveat=SaveAt(t1=True))`, with the
step (or the tolerance) a traced argument, so that each tool compiles once per problem:

1. `StormerVerlet()` (one RATTLE step, order 2), `Composition(order=4)` and
   `Composition(order=6)` (symmetric compositions of RATTLE steps), constant steps;
2. `CGVI(k)`, `k = 1, 2, 3` (the constrained Lobatto IIIA-IIIB Galerkin step, order `2k`;
   `CGVI(1)` is RATTLE solved as one Newton system), constant steps;
3. `diffrax.Dopri8` with a `PIDController` in the angle coordinates, where the constraints
   hold by construction (the chain's joint angles as in `benchmarks.constrained_chain`; the
   pendulum's polar and azimuthal angles).

The error is the max-norm of `(q, p)` at T against `problem.reference([T])`. Each run is
called once untimed (compiling), then `--repeats` times; the best time is quoted. The summary
gives, for each target error, the fastest run of each family that reaches it, and the time of
the fastest RATTLE composition as a multiple of the fastest `CGVI(k)` and of Dopri8.

    .venv/bin/python -m benchmarks.rattle_chain [--quick] [--repeats 5] [--out FILE]

`--quick` (one step per tool, two repeats, no file) is a smoke run.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import sys

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402

from .constrained_chain import ChainAngles, source_revision, state_error  # noqa: E402
from .peers_side_by_side import Out, fmt_s, timed_jax  # noqa: E402

DEFAULT_OUT = os.path.join("benchmarks", "results", "rattle_chain.txt")
TARGETS = (1e-4, 1e-6, 1e-8, 1e-10)

# Constant steps of each tool, per problem (T = 10).
FULL = dict(
    steps={
        "StormerVerlet": (0.01, 0.005, 0.0025, 0.00125),
        "Composition(4)": (0.04, 0.02, 0.01, 0.005),
        "Composition(6)": (0.1, 0.05, 0.025, 0.0125),
        "CGVI(1)": (0.01, 0.005, 0.0025),
        "CGVI(2)": (0.1, 0.05, 0.025, 0.0125),
        "CGVI(3)": (0.2, 0.1, 0.05, 0.025),
    },
    dopri8=(1e-6, 1e-8, 1e-10, 1e-12),
    repeats=5,
)
QUICK = dict(
    steps={"StormerVerlet": (0.01,), "Composition(4)": (0.04,), "Composition(6)": (0.1,),
           "CGVI(2)": (0.1,)},
    dopri8=(1e-8,),
    repeats=2,
)
SOLVERS = {
    "StormerVerlet": dvi.StormerVerlet,
    "Composition(4)": lambda: dvi.Composition(order=4),
    "Composition(6)": lambda: dvi.Composition(order=6),
    "CGVI(1)": lambda: dvi.CGVI(1),
    "CGVI(2)": lambda: dvi.CGVI(2),
    "CGVI(3)": lambda: dvi.CGVI(3),
}


class SphereAngles:
    """The spherical pendulum in its angles `(θ, φ)` (`θ` from the downward vertical):
    `θ̈ = sin θ cos θ φ̇² − (g/ℓ) sin θ`, `φ̈ = −2 cot θ θ̇ φ̇`, the equations of the problem's
    reference."""

    def __init__(self, problem):
        self.g_over_l = problem.params["g"] / problem.params["length"]
        self.y0 = np.asarray(problem.reference_flow.y0, np.float64)
        self._to_state = problem.reference_flow.to_state

    def jax_field(self, t, y, args):
        theta, _, dtheta, dphi = y
        s, c = jnp.sin(theta), jnp.cos(theta)
        return jnp.stack([dtheta, dphi, s * c * dphi**2 - self.g_over_l * s,
                          -2 * c / s * dtheta * dphi])

    def to_state(self, y):
        q, p = self._to_state(np.asarray(y, np.float64)[None])
        return q[0], p[0]


def constant_step_rows(problem, reference, name, steps, max_steps, repeats, out):
    solver = SOLVERS[name]()

    @eqx.filter_jit
    def solve(y0, dt):
        sol = diffrax.diffeqsolve(problem.term, solver, problem.t0, problem.t1, dt, y0,
                                  args=problem.args, saveat=diffrax.SaveAt(t1=True),
                                  max_steps=max_steps, throw=False)
        return sol.ys, sol.result == diffrax.RESULTS.successful

    rows = []
    for h in steps:
        ((q, p), ok), compile_s, best, _ = timed_jax(solve, problem.y0, jnp.asarray(h),
                                                     repeats=repeats)
        err = state_error(np.asarray(q)[-1], np.asarray(p)[-1], reference)
        status = "ok" if bool(ok) and math.isfinite(err) else "failed"
        rows.append(dict(tool=name, setting=f"dt = {h:g}", error=err, best=best,
                         compile=compile_s, status=status))
        print_row(out, rows[-1])
    return rows


def dopri8_rows(angles, reference, problem, rtols, repeats, out):
    term = diffrax.ODETerm(angles.jax_field)

    @jax.jit
    def solve(y0, rtol):
        sol = diffrax.diffeqsolve(
            term, diffrax.Dopri8(), problem.t0, problem.t1, None, y0,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            saveat=diffrax.SaveAt(t1=True), max_steps=2**18, throw=False)
        return sol.ys, sol.result == diffrax.RESULTS.successful

    rows = []
    for rtol in rtols:
        (y, ok), compile_s, best, _ = timed_jax(solve, jnp.asarray(angles.y0),
                                                jnp.asarray(rtol), repeats=repeats)
        q, p = angles.to_state(np.asarray(y)[-1])
        err = state_error(q, p, reference)
        rows.append(dict(tool="Dopri8 (angles)", setting=f"rtol = atol = {rtol:g}", error=err,
                         best=best, compile=compile_s,
                         status="ok" if bool(ok) and math.isfinite(err) else "failed"))
        print_row(out, rows[-1])
    return rows


def print_row(out, row) -> None:
    out(f"| {row['tool']} | {row['setting']} | {row['error']:.1e} | {fmt_s(row['best'])} | "
        f"{row['compile']:.1f} s | {row['status']} |")


def family(row) -> str:
    tool = row["tool"]
    if tool.startswith(("StormerVerlet", "Composition")):
        return "RATTLE"
    return "CGVI" if tool.startswith("CGVI") else "Dopri8"


def equal_error(rows, out) -> None:
    """For each target, the fastest run of each family reaching it, and RATTLE's time as a
    multiple of the others'."""
    families = ("RATTLE", "CGVI", "Dopri8")
    out()
    out("Wall time at equal error (best of the repeats; fastest run of each family with "
        "error <= target):")
    out()
    out("| target | RATTLE (StormerVerlet, Composition) | CGVI(k) | Dopri8 (angles) | "
        "RATTLE / CGVI | RATTLE / Dopri8 |")
    out("|---|---|---|---|---|---|")
    for target in TARGETS:
        best = {}
        for fam in families:
            ok = [r for r in rows if family(r) == fam and r["status"] == "ok"
                  and r["error"] <= target]
            best[fam] = min(ok, key=lambda r: r["best"]) if ok else None
        cells = [f"{r['tool']} {r['setting']}: {fmt_s(r['best'])} ({r['error']:.0e})"
                 if r else "not reached" for r in (best[f] for f in families)]
        ratios = []
        for other in ("CGVI", "Dopri8"):
            if best["RATTLE"] and best[other]:
                ratios.append(f"{best['RATTLE']['best'] / best[other]['best']:.2f}x")
            else:
                ratios.append("-")
        out(f"| {target:.0e} | " + " | ".join(cells + ratios) + " |")


def run_problem(problem, angles, config, repeats, out) -> None:
    q_ref, p_ref = problem.reference(np.array([problem.t1]))
    reference = (q_ref[0], p_ref[0])
    out()
    out(f"## {problem.name} ({problem.params}), T = {problem.t1:g}")
    out()
    out("| tool | setting | error | best | compile | status |")
    out("|---|---|---|---|---|---|")
    rows = []
    for name, steps in config["steps"].items():
        max_steps = int(round((problem.t1 - problem.t0) / min(steps))) + 4
        rows += constant_step_rows(problem, reference, name, steps, max_steps, repeats, out)
    rows += dopri8_rows(angles, reference, problem, config["dopri8"], repeats, out)
    equal_error(rows, out)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run (one step per tool)")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed runs after the first (default 5; 2 with --quick)")
    parser.add_argument("--out", default=None,
                        help=f"write the output here (default {DEFAULT_OUT}; none with --quick)")
    args = parser.parse_args(argv)
    config = QUICK if args.quick else FULL
    repeats = args.repeats if args.repeats is not None else config["repeats"]
    if repeats < 1:
        parser.error("--repeats must be at least 1")
    path = args.out if args.out is not None else (None if args.quick else DEFAULT_OUT)
    command = ("python -m benchmarks.rattle_chain "
               + " ".join(sys.argv[1:] if argv is None else argv)).rstrip()
    out = Out()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    out(f"# RATTLE compositions against CGVI(k) and Dopri8 ({datetime.date.today()}, "
        f"{platform.machine()}, {os.cpu_count()} CPUs, load average {load:.1f} at start)")
    out(f"# diffrax_vi {source_revision()}, jax {jax.__version__}, diffrax "
        f"{diffrax.__version__}; float64; one process; command: {command}")
    chain = problems.rigid_chain(dtype=jnp.float64)
    run_problem(chain, ChainAngles(chain), config, repeats, out)
    sphere = problems.spherical_pendulum(dtype=jnp.float64)
    run_problem(sphere, SphereAngles(sphere), config, repeats, out)
    if path:
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        out.save(path)
        print(f"# written to {path}")


if __name__ == "__main__":
    main()
