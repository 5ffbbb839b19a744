"""The constrained rigid chain side by side, in one process (issue 53): wall time at equal error.

The problem is `problems.rigid_chain()` (5 planar links, gravity, joint damping 0.05, T = 10).
Three tools integrate it:

1. `CGVI(k)` in Cartesian coordinates `q = (x1, y1, ..., x5, y5)` with the five length
   constraints and their multipliers (the constrained Lobatto IIIA-IIIB Galerkin step, order
   2k), constant steps; its holonomic drift (the largest `|g|` and `|G v|` of the run) is read
   from `sol.solver_state.holonomic_drift`.
2. `diffrax.Dopri8` with a `PIDController` on the chain's ODE in joint angles,
   `M(θ) θ̈ = −C(θ, θ̇) − ∂V/∂θ + Q(θ̇)` (the equations of the problem's reference, written
   here in JAX with `jnp.linalg.solve`). In angle coordinates the constraints hold by
   construction: the drift printed is that of the final state mapped to `(q, p)`, round-off.
3. heyoka's `taylor_adaptive` on the same angle ODE, its right-hand side built as heyoka
   expressions (the 5 x 5 mass-matrix solve as symbolic Gaussian elimination, which heyoka's
   decomposition shares by common-subexpression elimination).

Two more measurements follow in the same process (issue 65):

- the spherical pendulum (`problems.spherical_pendulum()`, T = 10): `CGVI(k)` in Cartesian
  coordinates with its constraint against `Dopri8` in the spherical angles `(θ, φ)`, the
  angle states mapped to `(q, p)`; the ratio at equal error 1e-9 and 1e-12;
- one step: `CGVI(4)` at one `dt` on the 5- and 20-link chains (constrained) and on the
  5-link chain's 10 coordinates with stiff springs for rods and no constraint (the
  unconstrained engine, `_step.jacobian_free`): each solve's median over its steps, the updates
  per step, and the ratios constrained / engine and 20 links / 5 links.

The error is the max-norm of `(q, p)` at T against `problem.reference([T])` (extended-precision
extrapolation in the angles, mapped to `(q, p)`); the angle solvers' final states are mapped by
`problems.chain_angles_to_state` in float64. Timings follow `benchmarks.peers_side_by_side`:
our solvers are `jax.jit` around the whole `diffeqsolve(..., saveat=SaveAt(t1=True))`, heyoka
is built once per tolerance without its compiled-code caches; each is run once untimed, then
`--repeats` times (heyoka's `propagate_until` from a fresh copy of the start each time); the
median is quoted, the best beside it, and "compile" is the first call less the best run.
The summary gives, for each target error, the fastest run of each tool that reaches it and
its time as a multiple of heyoka's.

    .venv/bin/python -m benchmarks.constrained_chain [--quick] [--repeats 5] [--json FILE]

`--quick` (one CGVI degree and two steps, one tolerance each, a short per-step run, two
repeats) is a smoke run of about a minute, mostly compilation; it writes no JSON unless
`--json` is given.
Without heyoka (the `peers` extra) its part is skipped and the ratios are not given.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import peers  # noqa: E402

from .peers_side_by_side import Out, fmt_s, timed_jax  # noqa: E402

DEFAULT_JSON = os.path.join("benchmarks", "results", "constrained_chain.json")
TARGETS = (1e-6, 1e-9, 1e-12)

FULL = dict(
    cgvi={2: (0.025, 0.0125), 4: (0.2, 0.1, 0.05, 0.025), 5: (0.2, 0.1, 0.05),
          6: (0.4, 0.2, 0.1, 0.05)},
    dopri8=(1e-6, 1e-8, 1e-10, 1e-12, 1e-13),
    heyoka=(1e-9, 1e-12, 1e-15),
    sphere_cgvi={4: (0.2, 0.1, 0.05), 5: (0.2, 0.1, 0.05), 6: (0.4, 0.2, 0.1)},
    sphere_dopri8=(1e-8, 1e-10, 1e-11, 1e-12, 1e-13),
    per_step=dict(degree=4, dt=0.025, steps=200, links=(5, 20)),
    repeats=5,
)
QUICK = dict(cgvi={4: (0.2, 0.1)}, dopri8=(1e-10,), heyoka=(1e-12,),
             sphere_cgvi={4: (0.1,)}, sphere_dopri8=(1e-10,),
             per_step=dict(degree=4, dt=0.05, steps=40, links=(5, 20)), repeats=2)
# The equal-error ratios the issue (65) asks of the spherical pendulum.
SPHERE_TARGETS = (1e-9, 1e-12)


# -- the chain in joint angles ----------------------------------------------------------------
class ChainAngles:
    """The chain's constants, as `problems.rigid_chain` sets them, and its angle equations
    `M(θ) θ̈ = −C − ∂V/∂θ + Q` (those of the problem's reference field) for JAX and heyoka."""

    def __init__(self, problem):
        par = problem.params
        self.n = n = par["n_links"]
        self.masses = (par["mass"],) * n
        self.lengths = (par["length"],) * n
        self.g, self.damping = par["g"], par["damping"]
        self.tail = np.cumsum(np.asarray(self.masses)[::-1])[::-1]  # μ_i = Σ_{k ≥ i} m_k
        self.y0 = np.asarray(problem.reference_flow.y0, np.float64)  # (θ, θ̇) at t0

    def coefficient(self, i: int, j: int) -> float:
        """`μ_max(i,j) ℓ_i ℓ_j`, the factor of `cos(θ_i − θ_j)` in `M_ij`."""
        return float(self.tail[max(i, j)] * self.lengths[i] * self.lengths[j])

    def jax_field(self, t, y, args):
        n = self.n
        theta, omega = y[:n], y[n:]
        ell = jnp.asarray(self.lengths, y.dtype)
        idx = np.arange(n)
        mu = jnp.asarray(self.tail[np.maximum(idx[:, None], idx[None, :])], y.dtype)
        diff = theta[:, None] - theta[None, :]
        lij = ell[:, None] * ell[None, :]
        mass = mu * lij * jnp.cos(diff)
        coriolis = jnp.sum(mu * lij * jnp.sin(diff) * omega[None, :] ** 2, axis=-1)
        gravity = self.g * jnp.asarray(self.tail, y.dtype) * ell * jnp.sin(theta)
        slip = omega - jnp.concatenate([jnp.zeros_like(omega[:1]), omega[:-1]])
        ahead = jnp.concatenate([slip[1:], jnp.zeros_like(slip[:1])])
        torque = -self.damping * (slip - ahead)
        accel = jnp.linalg.solve(mass, torque - coriolis - gravity)
        return jnp.concatenate([omega, accel])

    def heyoka_system(self):
        """`[(variable, expression), ...]`: the same equations as heyoka expressions, the
        mass-matrix solve by Gaussian elimination without pivoting (M is symmetric positive
        definite) on expressions."""
        hy = peers.require_heyoka()
        n = self.n
        names = [f"th{i}" for i in range(n)] + [f"w{i}" for i in range(n)]
        variables = list(hy.make_vars(*names))
        theta, omega = variables[:n], variables[n:]
        cos, sin = {}, {}
        for i in range(n):
            for j in range(i + 1, n):
                cos[i, j] = hy.cos(theta[i] - theta[j])
                sin[i, j] = hy.sin(theta[i] - theta[j])
        squares = [w * w for w in omega]

        def c(i, j):
            return hy.expression(1.0) if i == j else cos[min(i, j), max(i, j)]

        def s(i, j):  # sin(θ_i − θ_j), antisymmetric
            return sin[i, j] if i < j else -sin[j, i]

        a = [[self.coefficient(i, j) * c(i, j) if i != j
              else hy.expression(self.coefficient(i, i)) for j in range(n)] for i in range(n)]
        slip = [omega[0]] + [omega[i] - omega[i - 1] for i in range(1, n)]
        rhs = []
        for i in range(n):
            torque = -self.damping * (slip[i] - slip[i + 1]) if i + 1 < n \
                else -self.damping * slip[i]
            coriolis = hy.sum([self.coefficient(i, j) * s(i, j) * squares[j]
                               for j in range(n) if j != i])
            gravity = (self.g * float(self.tail[i]) * self.lengths[i]) * hy.sin(theta[i])
            rhs.append(torque - coriolis - gravity)
        for k in range(n):  # forward elimination
            for i in range(k + 1, n):
                factor = a[i][k] / a[k][k]
                for j in range(k + 1, n):
                    a[i][j] = a[i][j] - factor * a[k][j]
                rhs[i] = rhs[i] - factor * rhs[k]
        accel = [None] * n
        for k in range(n - 1, -1, -1):  # back substitution
            known = [a[k][j] * accel[j] for j in range(k + 1, n)]
            accel[k] = (rhs[k] - hy.sum(known) if known else rhs[k]) / a[k][k]
        return list(zip(variables, list(omega) + accel, strict=True))

    def to_state(self, y) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(y, np.float64)
        return problems.chain_angles_to_state(self.masses, self.lengths, y[: self.n],
                                              y[self.n:])

    def drift(self, q, p) -> tuple[float, float]:
        """`(max |g|, max |G v|)` of a Cartesian state, the constraint's two levels."""
        r = np.asarray(q, np.float64).reshape(-1, 2)
        v = (np.asarray(p, np.float64).reshape(-1, 2) / np.asarray(self.masses)[:, None])
        d = r - np.concatenate([np.zeros((1, 2)), r[:-1]])
        w = v - np.concatenate([np.zeros((1, 2)), v[:-1]])
        g = 0.5 * (np.sum(d * d, axis=1) - np.asarray(self.lengths) ** 2)
        return float(np.max(np.abs(g))), float(np.max(np.abs(np.sum(d * w, axis=1))))


# -- the runs ---------------------------------------------------------------------------------
def state_error(q, p, reference) -> float:
    q_ref, p_ref = reference
    return float(max(np.max(np.abs(np.asarray(q, np.float64) - q_ref)),
                     np.max(np.abs(np.asarray(p, np.float64) - p_ref))))


def make_row(tool, setting, steps, err, timing, drift, status="ok", **extra) -> dict:
    compile_s, best, median = timing
    return dict(tool=tool, setting=setting, steps=int(steps), error=err, wall_median_s=median,
                wall_best_s=best, compile_s=compile_s, drift_g=drift[0], drift_Gv=drift[1],
                status=status, **extra)


def cgvi_rows(problem, reference, grid, repeats, out, tool="CGVI") -> list[dict]:
    term, t0, t1 = problem.term, problem.t0, problem.t1
    rows = []
    for degree, steps_sizes in grid.items():
        for h in steps_sizes:
            steps = round((t1 - t0) / h)

            @jax.jit
            def solve(y0, degree=degree, h=h, steps=steps):
                sol = diffrax.diffeqsolve(
                    term, dvi.CGVI(degree), t0, t1, h, y0, args=problem.args,
                    saveat=diffrax.SaveAt(t1=True, solver_state=True), max_steps=steps + 2,
                    throw=False)
                return (sol.ys, sol.result == diffrax.RESULTS.successful,
                        sol.stats["num_steps"], sol.solver_state.holonomic_drift)

            setting = f"dt = {h:g}"
            try:
                ((q, p), ok, taken, drift), compile_s, best, median = timed_jax(
                    solve, problem.y0, repeats=repeats)
            except Exception as e:  # a configuration that cannot run is a row, not the end
                out(f"CGVI({degree}) {setting}: {type(e).__name__}: {str(e).splitlines()[0]}")
                continue
            err = state_error(np.asarray(q)[-1], np.asarray(p)[-1], reference)
            drift = np.asarray(drift, np.float64).reshape(-1, 2)[-1]
            status = "ok" if bool(ok) and math.isfinite(err) else "failed"
            rows.append(make_row(f"{tool}({degree})", setting, taken, err,
                                 (compile_s, best, median), tuple(map(float, drift)), status,
                                 coordinates="Cartesian + multipliers", order=2 * degree,
                                 drift_note="largest over the run (solver state)"))
            print_row(out, rows[-1])
    return rows


def timed_dopri8(term, problem, y0, rtol, repeats):
    """Dopri8 on the angle coordinates' `term` from `y0` over the problem's span, at
    rtol = atol = `rtol`, timed: `((ys, ok, steps), compile_s, best, median)`."""

    @jax.jit
    def solve(y0):
        sol = diffrax.diffeqsolve(
            term, diffrax.Dopri8(), problem.t0, problem.t1, None, y0,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            saveat=diffrax.SaveAt(t1=True), max_steps=2**20, throw=False)
        return sol.ys, sol.result == diffrax.RESULTS.successful, sol.stats["num_steps"]

    return timed_jax(solve, y0, repeats=repeats)


def dopri8_rows(chain, problem, reference, rtols, repeats, out) -> list[dict]:
    term = diffrax.ODETerm(chain.jax_field)
    y0 = jnp.asarray(chain.y0)
    rows = []
    for rtol in rtols:
        (y, ok, taken), compile_s, best, median = timed_dopri8(term, problem, y0, rtol, repeats)
        q, p = chain.to_state(np.asarray(y)[-1])
        err = state_error(q, p, reference)
        rows.append(make_row("Dopri8 (angles)", f"rtol = atol = {rtol:g}", taken, err,
                             (compile_s, best, median), chain.drift(q, p),
                             "ok" if bool(ok) and math.isfinite(err) else "failed",
                             coordinates="joint angles",
                             drift_note="zero by construction; the final state mapped to "
                                        "(q, p), round-off"))
        print_row(out, rows[-1])
    return rows


def heyoka_rows(chain, problem, reference, tols, repeats, out) -> list[dict]:
    hy = peers.require_heyoka()
    start = time.perf_counter()
    system = chain.heyoka_system()
    out(f"# heyoka system built in {time.perf_counter() - start:.2f} s")
    t0, t1 = float(problem.t0), float(problem.t1)
    rows = []
    for tol in tols:
        cache = hy.llvm_state
        enabled = cache.get_diskcache_enabled()
        cache.set_diskcache_enabled(False)  # a first compilation, as JAX's without a cache
        cache.clear_memcache()
        try:
            start = time.perf_counter()
            ta = hy.taylor_adaptive(system, chain.y0.copy(), time=t0, tol=tol)
            build_s = time.perf_counter() - start
        finally:
            cache.set_diskcache_enabled(enabled)

        def run():
            ta.time = t0
            ta.state[:] = chain.y0  # a fresh copy of the start
            return ta.propagate_until(t1)

        start = time.perf_counter()
        run()  # warm-up
        first = time.perf_counter() - start
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            res = run()
            times.append(time.perf_counter() - start)
        best, median = min(times), statistics.median(times)
        q, p = chain.to_state(np.array(ta.state))
        err = state_error(q, p, reference)
        status = "ok" if res[0] == hy.taylor_outcome.time_limit and math.isfinite(err) \
            else f"failed ({res[0].name})"
        rows.append(make_row(f"heyoka (order {ta.order})", f"tol = {tol:g}", res[3], err,
                             (build_s, best, median), chain.drift(q, p), status,
                             coordinates="joint angles", first_run_s=first,
                             drift_note="zero by construction; the final state mapped to "
                                        "(q, p), round-off"))
        print_row(out, rows[-1])
    return rows


def check_fields(chain, problem, out) -> None:
    """The JAX and heyoka angle fields against the reference's own (NumPy) field at the start
    and at a perturbed state."""
    rng = np.random.default_rng(0)
    states = [chain.y0, chain.y0 + rng.normal(scale=0.5, size=chain.y0.shape)]
    field = problem.reference_flow.rhs
    text = []
    for y in states:
        want = field(y[None, :].astype(np.float64))[0]
        got = np.asarray(chain.jax_field(0.0, jnp.asarray(y), None))
        text.append(f"JAX {np.max(np.abs(got - want)):.1e}")
        if peers.heyoka_available():
            hy = peers.require_heyoka()
            system = chain.heyoka_system()
            cf = hy.cfunc([e for _, e in system], [v for v, _ in system])
            text.append(f"heyoka {np.max(np.abs(cf(y) - want)):.1e}")
    out("# angle fields against the reference's field at the start and a perturbed state: "
        + ", ".join(text))


def reference_check(chain, problem, reference, out) -> float | None:
    """heyoka in long double (tol 1e-19) against the reference: how far the reference can be
    trusted."""
    if not peers.heyoka_available():
        return None
    hy = peers.require_heyoka()
    ta = hy.taylor_adaptive(chain.heyoka_system(), chain.y0.astype(np.longdouble),
                            time=np.longdouble(problem.t0), tol=np.longdouble(1e-19),
                            fp_type=np.longdouble)
    ta.propagate_until(np.longdouble(problem.t1))
    y = np.array(ta.state, np.longdouble)
    q, p = problems.chain_angles_to_state(chain.masses, chain.lengths, y[: chain.n],
                                          y[chain.n:])
    gap = state_error(q, p, reference)
    out(f"# reference check: heyoka long double (tol 1e-19, order {ta.order}) differs from "
        f"problem.reference by {gap:.1e} at T")
    return gap


def source_revision() -> str:
    """The commit of the working tree, `+changes` where `diffrax_vi/` differs from it."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", root, "status", "--porcelain", "diffrax_vi"],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+changes" if dirty else "")


# -- the spherical pendulum: Cartesian with its constraint, against Dopri8 in its angles ----
def sphere_angle_field(t, y, args):
    """`(θ, φ, θ̇, φ̇)'` of `problems.spherical_pendulum()` (g/ℓ = 9.81), in JAX."""
    theta, _, dtheta, dphi = y[0], y[1], y[2], y[3]
    s, c = jnp.sin(theta), jnp.cos(theta)
    return jnp.stack([dtheta, dphi, s * c * dphi**2 - 9.81 * s, -2 * c / s * dtheta * dphi])


def sphere_rows(grid_cgvi, rtols, repeats, out) -> list[dict]:
    problem = problems.spherical_pendulum(dtype=jnp.float64)
    q_ref, p_ref = problem.reference(np.array([problem.t1]))
    reference = (q_ref[0], p_ref[0])
    rows = cgvi_rows(problem, reference, grid_cgvi, repeats, out, tool="sphere CGVI")
    term = diffrax.ODETerm(sphere_angle_field)
    y0 = jnp.asarray(problem.reference_flow.y0, jnp.float64)
    to_cartesian = problem.reference_flow.to_state
    for rtol in rtols:
        (y, ok, taken), compile_s, best, median = timed_dopri8(term, problem, y0, rtol, repeats)
        q, p = to_cartesian(np.asarray(y, np.float64)[-1:])
        err = state_error(q[0], p[0], reference)
        drift = (abs(float(q[0] @ q[0]) - 1.0) / 2, abs(float(q[0] @ p[0])))
        rows.append(make_row("sphere Dopri8 (angles)", f"rtol = atol = {rtol:g}", taken, err,
                             (compile_s, best, median), drift,
                             "ok" if bool(ok) and math.isfinite(err) else "failed",
                             coordinates="spherical angles"))
        print_row(out, rows[-1])
    out()
    out("## Spherical pendulum at equal error (median; fastest CGVI / fastest Dopri8)")
    out()
    for target in SPHERE_TARGETS:
        best = {}
        for tool in ("sphere CGVI", "sphere Dopri8"):
            ok = [r for r in rows if r["tool"].startswith(tool) and r["status"] == "ok"
                  and r["error"] <= target]
            best[tool] = min(ok, key=lambda r: r["wall_median_s"]) if ok else None
        c, d = best["sphere CGVI"], best["sphere Dopri8"]
        if c and d:
            out(f"- {target:.0e}: {c['tool']} {c['setting']} {fmt_s(c['wall_median_s'])} "
                f"({c['error']:.0e}) / Dopri8 {d['setting']} {fmt_s(d['wall_median_s'])} "
                f"({d['error']:.0e}) = {c['wall_median_s'] / d['wall_median_s']:.2f}x")
        else:
            out(f"- {target:.0e}: not reached by " + ", ".join(k for k, v in best.items() if not v))
    return rows


# -- one step: constrained against the unconstrained engine, 5 links against 20 --------------
class SpringChain(eqx.Module):
    """The chain's points and gravity with stiff springs (k = 100) for its rods and no
    constraint: the same 2N coordinates, stepped by the unconstrained engine."""

    def __call__(self, t, q, v, args):
        r = q.reshape(-1, 2)
        d = r - jnp.concatenate([jnp.zeros_like(r[:1]), r[:-1]])
        stretch = jnp.sqrt(jnp.sum(d * d, axis=1)) - 1.0
        return 0.5 * v @ v - 9.81 * jnp.sum(r[:, 1]) - 50.0 * jnp.sum(stretch**2)


def per_step_rows(config, repeats, out) -> list[dict]:
    """The time of one step (the whole solve's median over its steps), `CGVI(degree)` at one
    `dt`: the damped chain of each number of links, and the 5-link chain's points on springs
    without constraints (the unconstrained engine, `_step.jacobian_free`)."""
    degree, dt, steps = config["degree"], config["dt"], config["steps"]
    cases = [(f"chain {n} links (constrained)", problems.rigid_chain(n_links=n))
             for n in config["links"]]
    spring = problems.rigid_chain(n_links=config["links"][0])
    cases.append((f"{2 * config['links'][0]} coordinates on springs (engine)",
                  dataclasses.replace(spring, term=dvi.LagrangianTerm(SpringChain()))))
    rows = []
    for name, problem in cases:
        @jax.jit
        def solve(y0, term=problem.term):
            sol = diffrax.diffeqsolve(term, dvi.CGVI(degree), 0.0, dt * steps, dt, y0,
                                      saveat=diffrax.SaveAt(t1=True, solver_state=True),
                                      max_steps=steps + 2,
                                      throw=False)
            return (sol.result == diffrax.RESULTS.successful, sol.stats["num_steps"],
                    sol.solver_state.iterations)

        (ok, taken, iterations), compile_s, best, median = timed_jax(solve, problem.y0,
                                                                     repeats=repeats)
        row = dict(case=name, degree=degree, dt=dt, steps=int(taken), ok=bool(ok),
                   updates_per_step=float(iterations) / max(int(taken), 1),
                   step_median_s=median / steps, step_best_s=best / steps, compile_s=compile_s)
        rows.append(row)
        out(f"| {name} | {int(taken)} | {row['updates_per_step']:.1f} | "
            f"{fmt_s(row['step_median_s'])} | {fmt_s(row['step_best_s'])} | "
            f"{'ok' if ok else 'failed'} |")
    c5, c20, engine = (r["step_median_s"] for r in rows)
    out()
    out(f"- constrained 5-link step / unconstrained engine step: {c5 / engine:.2f}x")
    out(f"- 20-link step / 5-link step: {c20 / c5:.2f}x")
    return rows


# -- output -----------------------------------------------------------------------------------
def print_row(out, row) -> None:
    out(f"| {row['tool']} | {row['setting']} | {row['steps']} | {row['error']:.1e} | "
        f"{fmt_s(row['wall_median_s'])} | {fmt_s(row['wall_best_s'])} | "
        f"{row['compile_s']:.2f} s | {row['drift_g']:.1e}, {row['drift_Gv']:.1e} | "
        f"{row['status']} |")


def family(row) -> str:
    return row["tool"].split(" (order")[0].split("(")[0].strip()


def equal_error(rows, out) -> list[dict]:
    """For each target, the fastest run (median) of each tool reaching it, and its ratio to
    heyoka's."""
    tools = ("CGVI", "Dopri8", "heyoka")
    summary = []
    out()
    out("## Wall time at equal error (median; fastest run of each tool with error <= target)")
    out()
    out("| target | " + " | ".join(tools) + " |")
    out("|---|" + "---|" * len(tools))
    for target in TARGETS:
        cells, entry = [], dict(target=target)
        best = {}
        for tool in tools:
            ok = [r for r in rows if family(r) == tool and r["status"] == "ok"
                  and r["error"] <= target]
            best[tool] = min(ok, key=lambda r: r["wall_median_s"]) if ok else None
        hey = best["heyoka"]
        for tool in tools:
            r = best[tool]
            if r is None:
                cells.append("not reached")
                entry[tool] = None
                continue
            ratio = r["wall_median_s"] / hey["wall_median_s"] if hey else None
            label = r["tool"] if tool != "heyoka" else "heyoka"
            text = f"{label} {r['setting']}: {fmt_s(r['wall_median_s'])} ({r['error']:.0e})"
            if ratio is not None and tool != "heyoka":
                text += f", {ratio:.1f}x"
            cells.append(text)
            entry[tool] = dict(tool=r["tool"], setting=r["setting"], error=r["error"],
                               wall_median_s=r["wall_median_s"], ratio_to_heyoka=ratio)
        out(f"| {target:.0e} | " + " | ".join(cells) + " |")
        summary.append(entry)
    return summary


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="a smoke run: CGVI(4) at two steps, one rtol, one tol, 2 repeats")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed runs after the warm-up (default 5; 2 with --quick)")
    parser.add_argument("--json", default=None,
                        help=f"write all rows here (default {DEFAULT_JSON}; none with --quick)")
    args = parser.parse_args(argv)
    config = QUICK if args.quick else FULL
    repeats = args.repeats if args.repeats is not None else config["repeats"]
    if repeats < 1:
        parser.error("--repeats must be at least 1")
    json_path = args.json if args.json is not None else (None if args.quick else DEFAULT_JSON)
    command = ("python -m benchmarks.constrained_chain "
               + " ".join(sys.argv[1:] if argv is None else argv)).rstrip()

    out = Out()
    have_heyoka = peers.heyoka_available()
    hy_version = getattr(peers.require_heyoka(), "__version__", "?") if have_heyoka \
        else "not installed"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    out(f"# constrained rigid chain side by side ({datetime.date.today()}, {platform.machine()}, "
        f"{os.cpu_count()} CPUs, load average {load:.1f} at start, python "
        f"{platform.python_version()})")
    revision = source_revision()
    out(f"# diffrax_vi {revision}, jax {jax.__version__}, diffrax {diffrax.__version__}, "
        f"heyoka {hy_version}; float64; one process; command: {command}")
    problem = problems.rigid_chain(dtype=jnp.float64)
    chain = ChainAngles(problem)
    start = time.perf_counter()
    q_ref, p_ref = problem.reference(np.array([problem.t1]))
    reference = (q_ref[0], p_ref[0])
    out(f"# {chain.n}-link chain, damping {chain.damping:g}, T = {problem.t1:g}; reference "
        f"({problem.reference_method}) in {time.perf_counter() - start:.1f} s")
    check_fields(chain, problem, out)
    gap = reference_check(chain, problem, reference, out) if not args.quick else None
    out()
    out("error: max-norm of (q, p) at T; wall: median (best) of "
        f"{repeats} runs after a warm-up; drift: (|g|, |G v|)")
    out()
    out("| tool | setting | steps | error | median | best | compile | drift | status |")
    out("|---|---|---|---|---|---|---|---|---|")
    rows = cgvi_rows(problem, reference, config["cgvi"], repeats, out)
    rows += dopri8_rows(chain, problem, reference, config["dopri8"], repeats, out)
    if have_heyoka:
        rows += heyoka_rows(chain, problem, reference, config["heyoka"], repeats, out)
    else:
        out(f"(heyoka skipped: {peers.MISSING_MESSAGE})")
    summary = equal_error(rows, out)
    out()
    out("## Spherical pendulum: CGVI in Cartesian coordinates, Dopri8 in spherical angles")
    out()
    out("| tool | setting | steps | error | median | best | compile | drift | status |")
    out("|---|---|---|---|---|---|---|---|---|")
    sphere = sphere_rows(config["sphere_cgvi"], config["sphere_dopri8"], repeats, out)
    out()
    out(f"## One step (CGVI({config['per_step']['degree']}), dt = {config['per_step']['dt']:g}, "
        f"{config['per_step']['steps']} steps; median over the solve)")
    out()
    out("| case | steps | updates / step | step (median) | step (best) | status |")
    out("|---|---|---|---|---|---|")
    per_step = per_step_rows(config["per_step"], repeats, out)
    if json_path:
        record = dict(command=command, date=str(datetime.date.today()),
                      machine=f"{platform.machine()}, {os.cpu_count()} CPUs",
                      load_average_at_start=load, diffrax_vi_revision=revision,
                      jax=jax.__version__,
                      diffrax=diffrax.__version__, heyoka=hy_version, dtype="float64",
                      problem=dict(name=problem.name, t1=problem.t1, **problem.params),
                      reference=problem.reference_method, reference_check_gap=gap,
                      repeats=repeats, targets=list(TARGETS), rows=rows, equal_error=summary,
                      spherical_pendulum=sphere, per_step=per_step)
        os.makedirs(os.path.dirname(json_path) or ".", exist_ok=True)
        with open(json_path, "w", encoding="utf-8") as f:
            json.dump(record, f, indent=1)
        out(f"# rows written to {json_path}")


if __name__ == "__main__":
    main()
