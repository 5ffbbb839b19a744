"""Long runs at the round-off limit (issue 28): energy growth and the cost of a step.

1. Energy: the harmonic oscillator at h = 0.5 over `--steps` steps (default 10^5), the running
   maximum of the relative energy error at 10^1 ... 10^k steps and its growth exponent over
   the last two decades (a log-log fit; Brouwer's law of random rounding is 0.5), for
   `CGVI(7)` in its default (projected) and reference (`FreeEndpoints`) forms and the default
   `NetworkVI` (tanh 10, GL8), each with `RoundoffNewton` stopping at `ftol` 64, 1 and 0
   (0: until the Newton updates stop shrinking).
2. Step cost: microseconds per constant step after compilation (median of 5 runs) of
   `CGVI(6)` in both forms and of `Dopri8`, on the oscillator (h = 0.5), Kepler with
   e = 0.5 (h = 2π/100) and the double pendulum (h = 0.05), with the mean Newton
   iterations per step and the final position error against the reference.
3. Growth on an ensemble (`--only growth`): `--members` oscillators of equal energy and spread
   phases over `--steps` steps, the RMS of their relative energy errors and its growth
   exponent from 10^3 steps on, for `CGVI(7)` with and without compensated summation, with
   and without `confirm`, by Newton, the chord and the kinetic iteration, and the default
   `NetworkVI`.
4. Compensated summation (`--only compensation`): the maximum energy error with and without
   it at small steps (oscillator h = 0.05, Kepler h = 2π/400 and 2π/100, float32).
5. Energy bias per step (`--only bias`): each step's end against the exact map (long double)
   of the same discrete Lagrangian from its start, along oscillator trajectories; the mean
   energy change rounding adds per step, per root finder, and the change of the determinant
   of the step's fitted linear map (`rounding_bias.map_deviation`). With `--nudge SEED ...`
   it measures instead `CGVI(7)`'s three Newton steps (ftol 1 with and without `confirm`,
   ftol 0) and its chord iteration to round-off with and without `predict` (with: its
   default) on the span as computed and on that span with each entry moved by -1, 0 or +1
   ulp at random (one draw per seed; the constant direction kept exact): how the bias
   depends on the span's last bits. With `--updates K ...` as well, Newton's iteration with
   exactly `K` updates per step and Newton to round-off (ftol 0), returning its last iterate
   or the one before, instead, then each root finder's mean bias over the spans: whether the
   number of updates or the stopping rule decides the bias.

    taskset -c 1 .venv/bin/python -m benchmarks.roundoff \\
        [--steps N] [--only energy|growth|compensation|cost|bias] [--members M]
        [--solver NAME] [--nudge SEED ...] [--updates K ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import equinox as eqx
import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import rounding_bias  # noqa: E402
from diffrax_vi.step_solve import FIRST_TRY  # noqa: E402


def energy_configs():
    out = {}
    for ftol in (64.0, 1.0, 0.0):
        rn = dvi.RoundoffNewton(ftol=ftol)
        out[f"CGVI(7), projected, ftol {ftol:g}"] = dvi.CGVI(7, root_finder=rn)
        out[f"CGVI(7), reference form, ftol {ftol:g}"] = dvi.CGVI(
            7, root_finder=rn, initial_trajectory_method=dvi.HermiteExtrapolation()
        )
        out[f"NetworkVI tanh 10, ftol {ftol:g}"] = dvi.NetworkVI(
            dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8), root_finder=rn
        )
    return out


def energy_growth(steps: int) -> None:
    problem = problems.harmonic_oscillator()
    h = 0.5
    marks = np.unique(np.round(np.geomspace(1, steps, 300)).astype(int))
    ts = jnp.asarray(np.concatenate([[0], marks]) * h)
    energy = jax.jit(jax.vmap(lambda q, p: problem.energy(0.0, q, p)))
    decades = [10**k for k in range(1, int(np.log10(steps)) + 1)]
    print(f"oscillator, h = {h}, {steps} steps: running max of the relative energy error")
    print("| solver | " + " | ".join(f"{d:g} steps" for d in decades)
          + " | growth exponent | iterations per step | us per step |")
    print("|---|" + "---|" * (len(decades) + 3))
    for name, solver in energy_configs().items():
        def run(y, solver=solver):
            return diffrax.diffeqsolve(
                problem.term, solver, 0.0, steps * h, h, y, args=problem.args,
                max_steps=steps, saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False,
            )
        run = jax.jit(run)
        sol = jax.block_until_ready(run(problem.y0))
        start = time.perf_counter()
        sol = jax.block_until_ready(run(problem.y0))
        us = (time.perf_counter() - start) / steps * 1e6
        e = np.asarray(energy(sol.ys[0], sol.ys[1]))
        err = np.maximum.accumulate(np.abs(e - e[0]) / abs(e[0]))
        done = np.asarray(ts) / h
        at = [err[np.searchsorted(done, d)] for d in decades]
        tail = done >= steps / 100
        slope = np.polyfit(np.log(done[tail]), np.log(np.maximum(err[tail], 1e-18)), 1)[0]
        its = int(sol.solver_state.iterations) / steps
        ok = sol.result == diffrax.RESULTS.successful
        print(f"| {name}{'' if ok else ' (failed)'} | " + " | ".join(f"{a:.1e}" for a in at)
              + f" | {slope:.2f} | {its:.2f} | {us:.1f} |", flush=True)


def growth_configs():
    return {
        "CGVI(7) (default: compensated, ftol 1, confirm)": dvi.CGVI(7),
        "CGVI(7), ftol 1 without confirm (the default before)": dvi.CGVI(
            7, root_finder=dvi.RoundoffNewton(ftol=1.0, confirm=False)
        ),
        "CGVI(7), compensated, ftol 0": dvi.CGVI(7, root_finder=dvi.RoundoffNewton(ftol=0.0)),
        "CGVI(7), chord, ftol 1": dvi.CGVI(7, root_finder=dvi.FixedPointIteration(ftol=1.0)),
        "CGVI(7), chord, ftol 0": dvi.CGVI(7, root_finder=dvi.FixedPointIteration(ftol=0.0)),
        "CGVI(7), chord, ftol 0, predict": dvi.CGVI(
            7, root_finder=dvi.FixedPointIteration(ftol=0.0, predict=True)
        ),
        "CGVI(7), kinetic fixed point, ftol 0": dvi.CGVI(
            7, root_finder=dvi.FixedPointIteration(ftol=0.0, matrix="kinetic")
        ),
        "CGVI(7), kinetic fixed point, ftol 1": dvi.CGVI(
            7, root_finder=dvi.FixedPointIteration(ftol=1.0, matrix="kinetic")
        ),
        "CGVI(7), uncompensated, ftol 1": dvi.CGVI(7, compensated=False),
        "CGVI(7), uncompensated, ftol 0": dvi.CGVI(
            7, compensated=False, root_finder=dvi.RoundoffNewton(ftol=0.0)
        ),
        "NetworkVI tanh 10 (default)": dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10)),
        "NetworkVI tanh 10, uncompensated": dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10),
                                                          compensated=False),
        "NetworkVI tanh 10, confirm": dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10),
                                                    root_finder=dvi.RoundoffNewton(confirm=True)),
    }


def energy_growth_ensemble(steps: int, members: int, only: str | None = None) -> None:
    """Brouwer's law measured on an ensemble: `members` oscillators of equal energy and
    spread phases, the root mean square over them of the relative energy error at
    log-spaced times, and its growth exponent fitted from 10^3 steps on (a single run's
    running maximum is too noisy to fit)."""
    problem = problems.harmonic_oscillator()
    h = 0.5
    m, k = 1.0, 0.5  # the library oscillator's defaults
    omega = (k / m) ** 0.5
    amplitude = float(problem.y0[0][0])
    phases = 2 * np.pi * (np.arange(members) + 0.1234) / members
    q0 = jnp.asarray(amplitude * np.cos(phases))[:, None]
    p0 = jnp.asarray(-m * omega * amplitude * np.sin(phases))[:, None]
    marks = np.unique(np.round(np.geomspace(10, steps, 60)).astype(int))
    ts = jnp.asarray(np.concatenate([[0], marks]) * h)
    energy = jax.jit(jax.vmap(jax.vmap(lambda q, p: problem.energy(0.0, q, p))))
    decades = [10**j for j in range(2, int(np.log10(steps)) + 1)]
    print(f"\noscillator ensemble ({members} phases), h = {h}, {steps} steps: RMS over the "
          "members of the relative energy error")
    print("| solver | " + " | ".join(f"{d:g} steps" for d in decades)
          + " | growth exponent (10^3 on, ± bootstrap SE) | us per step |")
    print("|---|" + "---|" * (len(decades) + 2))
    for name, solver in growth_configs().items():
        if only and only not in name:
            continue

        def run(q, p, solver=solver):
            return diffrax.diffeqsolve(
                problem.term, solver, 0.0, steps * h, h, (q, p), args=problem.args,
                max_steps=steps, saveat=diffrax.SaveAt(ts=ts), throw=False,
            )

        # one member at a time: a vmapped run is much slower on a CPU (every lane takes
        # the iterations of the slowest)
        run = jax.jit(run)
        jax.block_until_ready(run(q0[0], p0[0]))
        start = time.perf_counter()
        sols = [jax.block_until_ready(run(q, p)) for q, p in zip(q0, p0, strict=True)]
        us = (time.perf_counter() - start) / steps / members * 1e6
        e = np.stack([np.asarray(energy(s.ys[0][None], s.ys[1][None]))[0] for s in sols])
        result = np.stack([np.asarray(s.result == diffrax.RESULTS.successful) for s in sols])
        rel = np.abs(e - e[:, :1]) / np.abs(e[:, :1])
        rms = np.sqrt(np.mean(rel**2, axis=0))
        done = np.asarray(ts) / h
        at = [rms[np.argmin(np.abs(done - d))] for d in decades]
        tail = done >= 1000
        slope = _rms_growth_exponent(rel[:, tail], done[tail])
        # its standard error: the spread of the fit over members drawn again with replacement
        draws = np.random.default_rng(0).integers(0, members, (200, members))
        spread = np.std([_rms_growth_exponent(rel[d][:, tail], done[tail]) for d in draws])
        ok = bool(np.all(result))
        print(f"| {name}{'' if ok else ' (failed)'} | " + " | ".join(f"{a:.1e}" for a in at)
              + f" | {slope:.2f} ± {spread:.2f} | {us:.1f} |", flush=True)


def _rms_growth_exponent(rel, done):
    """Slope of log RMS (over the rows of `rel`) against log steps."""
    rms = np.sqrt(np.mean(rel**2, axis=0))
    return np.polyfit(np.log(done), np.log(np.maximum(rms, 1e-18)), 1)[0]


def compensation() -> None:
    """Maximum relative energy error with and without compensated summation, at steps whose
    increments are far below the state (and one where truncation dominates)."""
    cases = [
        ("oscillator, h = 0.05, CGVI(6)", problems.harmonic_oscillator(), 0.05, 40_000, 6,
         jnp.float64),
        ("Kepler e = 0.5, h = 2π/400, CGVI(6)", problems.kepler(eccentricity=0.5),
         2 * np.pi / 400, 40_000, 6, jnp.float64),
        ("Kepler e = 0.5, h = 2π/100, CGVI(6)", problems.kepler(eccentricity=0.5),
         2 * np.pi / 100, 10_000, 6, jnp.float64),
        ("oscillator, h = 0.05, CGVI(4), float32", problems.harmonic_oscillator(), 0.05,
         20_000, 4, jnp.float32),
    ]
    print("\ncompensated summation: maximum relative energy error (one run each)")
    print("| problem, solver | steps | compensated | plain | us per step (compensated / plain) |")
    print("|---|---|---|---|---|")
    for label, problem, h, steps, degree, dtype in cases:
        y0 = jax.tree_util.tree_map(lambda a, dtype=dtype: jnp.asarray(a, dtype), problem.y0)
        ts = jnp.asarray(np.linspace(0.0, steps * h, 501), dtype)
        e0 = float(problem.energy(0.0, *problem.y0))
        energy = jax.jit(jax.vmap(lambda q, p, problem=problem: problem.energy(0.0, q, p)))
        out = []
        for comp in (True, False):
            solver = dvi.CGVI(degree, compensated=comp)

            def run(ts, solver=solver, problem=problem, y0=y0, h=h, steps=steps, dtype=dtype):
                return diffrax.diffeqsolve(
                    problem.term, solver, ts[0], ts[-1], jnp.asarray(h, dtype), y0,
                    args=problem.args, saveat=diffrax.SaveAt(ts=ts), max_steps=steps + 10,
                )

            run = jax.jit(run)
            sol = jax.block_until_ready(run(ts))
            times = []
            for _ in range(3):
                start = time.perf_counter()
                jax.block_until_ready(run(ts))
                times.append(time.perf_counter() - start)
            e = np.asarray(energy(*(a.astype(jnp.float64) for a in sol.ys)))
            out.append((np.max(np.abs(e - e0)) / abs(e0), statistics.median(times) / steps * 1e6))
        print(f"| {label} | {steps} | {out[0][0]:.1e} | {out[1][0]:.1e} | "
              f"{out[0][1]:.1f} / {out[1][1]:.1f} |", flush=True)


def step_cost() -> None:
    cases = {
        "oscillator (h = 0.5)": (problems.harmonic_oscillator(), 0.5, 4000),
        "Kepler e = 0.5 (h = 2π/100)": (problems.kepler(eccentricity=0.5), 2 * np.pi / 100, 4000),
        "double pendulum (h = 0.05)": (problems.double_pendulum(), 0.05, 200),
    }
    print("\nstep cost on constant steps (median of 5 runs after compiling)")
    print("| problem | solver | us per step | / Dopri8 | iterations per step | final error |")
    print("|---|---|---|---|---|---|")
    for label, (problem, h, n) in cases.items():
        solvers = {
            "Dopri8": diffrax.Dopri8(),
            "CGVI(6)": dvi.CGVI(6),
            "CGVI(6), without confirm": dvi.CGVI(
                6, root_finder=dvi.RoundoffNewton(ftol=1.0, confirm=False)
            ),
            "CGVI(6), uncompensated": dvi.CGVI(6, compensated=False),
            "CGVI(6), chord": dvi.CGVI(6, root_finder=dvi.FixedPointIteration(ftol=1.0)),
            "CGVI(6), chord, LU": dvi.CGVI(
                6, root_finder=dvi.FixedPointIteration(ftol=1.0, inverse=False)
            ),
            "CGVI(6), ftol 0": dvi.CGVI(6, root_finder=dvi.RoundoffNewton(ftol=0.0)),
            "CGVI(6), reference form": dvi.CGVI(6, root_finder=dvi.LevenbergMarquardt()),
        }
        base = None
        q_ref, _ = problem.reference(np.array([n * h]))
        for name, solver in solvers.items():
            variational = isinstance(solver, dvi.NetworkVI)
            term = problem.term if variational else diffrax.ODETerm(problem.term.vf)

            def run(y, solver=solver, term=term, variational=variational):
                sol = diffrax.diffeqsolve(
                    term, solver, 0.0, n * h, h, y, args=problem.args, max_steps=n,
                    saveat=diffrax.SaveAt(t1=True, solver_state=variational), throw=False,
                )
                its = sol.solver_state.iterations if variational else jnp.zeros((), jnp.int32)
                return sol.ys[0][-1], sol.result == diffrax.RESULTS.successful, its

            run = jax.jit(run)
            q, ok, its = jax.block_until_ready(run(problem.y0))
            times = []
            for _ in range(5):
                start = time.perf_counter()
                jax.block_until_ready(run(problem.y0))
                times.append(time.perf_counter() - start)
            us = statistics.median(times) / n * 1e6
            base = base or us
            err = float(np.max(np.abs(np.asarray(q) - q_ref[-1])) / np.max(np.abs(q_ref[-1])))
            iters = f"{int(its) / n:.2f}" if variational else "-"
            status = "" if bool(ok) else " (failed)"
            print(f"| {label} | {name}{status} | {us:.1f} | {us / base:.2f} | {iters} "
                  f"| {err:.1e} |", flush=True)


def bias_configs():
    rf = dvi.RoundoffNewton
    fp = dvi.FixedPointIteration
    return {
        "Newton, ftol 1, without confirm (the default before)": dict(
            root_finder=rf(ftol=1.0, confirm=False)),
        "Newton, ftol 1, confirm": dict(root_finder=rf(ftol=1.0)),
        "Newton, ftol 0": dict(root_finder=rf(ftol=0.0)),
        "chord, ftol 1, without confirm": dict(root_finder=fp(ftol=1.0, confirm=False)),
        "chord, ftol 1": dict(root_finder=fp(ftol=1.0)),
        "chord, ftol 0": dict(root_finder=fp(ftol=0.0)),
        "chord, ftol 0, predict (CGVI's default)": dict(root_finder=fp(ftol=0.0, predict=True)),
        "kinetic, ftol 0": dict(root_finder=fp(ftol=0.0, matrix="kinetic")),
        "NetworkVI (tanh 10, GL8): default (ftol 64, without confirm)": dict(network=True),
        "NetworkVI: ftol 64, confirm": dict(network=True, root_finder=rf(ftol=64.0)),
        "NetworkVI: ftol 0": dict(network=True, root_finder=rf(ftol=0.0)),
    }


def _bias_solver(options, nudge: int | None = None):
    options = dict(options)
    if options.pop("network", False):
        return dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8),
                             compensated=False, **options)
    if nudge is None:
        return dvi.CGVI(7, compensated=False, **options)
    # CGVI(7)'s projected step (the same solver `dvi.CGVI` builds) on the nudged span
    return dvi.NetworkVI(dvi.LagrangeBasis(7), dvi.GaussLegendre(8),
                         formulation=_NudgedProjection(seed=nudge), compensated=False,
                         **options)


def nudge_span(span, seed: int):
    """`span` with each entry of `gq`, `gv`, `g0` and `gd` moved by -1, 0 or +1 ulp, drawn
    from `seed`; the constant direction (column 0) is kept exact."""
    rng = np.random.default_rng(seed)

    def nudge(a):
        a = np.asarray(a)
        steps = rng.integers(-1, 2, size=a.shape)
        steps[..., 0] = 0
        up, down = np.nextafter(a, np.inf), np.nextafter(a, -np.inf)
        return jnp.asarray(np.where(steps > 0, up, np.where(steps < 0, down, a)))

    parts = (span.gq, span.gv, span.g0, span.gd)
    return eqx.tree_at(lambda s: (s.gq, s.gv, s.g0, s.gd), span, tuple(map(nudge, parts)))


class _NudgedProjection(dvi.VariableProjection):
    """The projected step on its span nudged by `nudge_span(span, seed)`."""

    seed: int = eqx.field(static=True, default=0)

    def span(self, theta, ctx):
        return nudge_span(super().span(theta, ctx), self.seed)


def _span(solver, ctx):
    """The step's (compile-time constant) span."""
    form = solver.formulation
    if isinstance(solver.basis, dvi.ShallowNetBasis):
        hidden = form.hidden.parameters(solver.basis, 1, jnp.float64)
    else:
        hidden = jnp.zeros((solver.basis.num_params(), 1))
    return form.span(hidden, ctx)


class _FixedUpdates(dvi.RoundoffNewton):
    """`RoundoffNewton` that ends every solve after exactly `updates` full Newton updates,
    whatever the residual: how the bias depends on the number of updates alone, without a
    stopping rule choosing it (a study tool, not a root finder to use)."""

    updates: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if isinstance(self.updates, bool) or not isinstance(self.updates, int) or not (
            1 <= self.updates <= FIRST_TRY
        ):
            raise ValueError(f"updates must be an integer from 1 to {FIRST_TRY} (a solve not "
                             f"ended after {FIRST_TRY} updates restarts), got {self.updates!r}")

    def _update(self, fn, y, args, options, state):
        y, state, aux = super()._update(fn, y, args, options, state)
        done = state.iterations >= self.updates
        return y, dataclasses.replace(state, converged=done, at_floor=jnp.zeros_like(done)), aux

    def _ended(self, state):
        return state.iterations >= self.updates, optx.RESULTS.successful


class _BeforeLastUpdate(dvi.RoundoffNewton):
    """`RoundoffNewton` run to round-off (`ftol=0`) that returns the iterate before its last
    update, the one that did not shrink and ended the solve (a study tool)."""

    def __check_init__(self):
        if self.ftol != 0:
            raise ValueError(f"_BeforeLastUpdate runs to round-off: ftol must be 0, got "
                             f"{self.ftol!r}")

    def _update(self, fn, y, args, options, state):
        new, state, aux = super()._update(fn, y, args, options, state)
        kept = jax.tree_util.tree_map(lambda a, b: jnp.where(state.at_floor, a, b), y, new)
        return kept, state, aux


def energy_bias(steps: int, members: int, nudges: list[int] | None = None,
                updates: list[int] | None = None) -> None:
    """Where the energy drift comes from: along `members` oscillator trajectories of `steps`
    uncompensated `CGVI(7)` (or default network) steps (h = 0.5), each step's end is
    compared with the exact map of the same discrete Lagrangian applied to its start
    (`rounding_bias`, long double). The mean of the energy change that rounding adds per
    step is the drift rate; Brouwer's law needs it to vanish (against its standard error),
    leaving a random walk. The `det(M) change` column is the change of the determinant of
    the step's fitted linear map (`rounding_bias.map_deviation`), which accounts for that
    mean; the last, the root finder's updates per step. Given
    `nudges`, `CGVI(7)`'s three Newton steps (ftol 1 with and without `confirm`, ftol 0) and
    its chord iteration to round-off with and without `predict` (with: its default) on the
    span as computed and nudged by each seed (`nudge_span`); given also `updates`, Newton
    with exactly each number of updates (`_FixedUpdates`) and to round-off (ftol 0), the
    latter also returning the iterate before its last update (`_BeforeLastUpdate`), instead.
    A run over several spans ends with each root finder's mean bias over the spans."""
    h, m, k = 0.5, 1.0, 0.5
    phases = 2 * np.pi * (np.arange(members) + 0.1234) / members
    print(f"\nenergy bias per step: oscillator, h = {h}, uncompensated, {members} "
          f"trajectories of {steps} steps; mean and standard error over all steps of "
          "(E(end) - E(exact map of start)) / E0, in units of eps; det(M) change: of the "
          "step's fitted linear map, in eps; iterations: the root finder's updates per step")
    print("| root finder | span | mean | standard error | mean / standard error | "
          "RMS per step | drift over the run (mean x steps, relative) | det(M) change "
          "| iterations per step (mean) |")
    print("|---|---|---|---|---|---|---|---|---|")
    eps = float(np.finfo(np.float64).eps)
    configs = bias_configs()
    if updates:
        configs = {
            **{f"Newton, exactly {n} updates": dict(root_finder=_FixedUpdates(ftol=0.0,
                                                                                updates=n))
               for n in updates},
            "Newton, ftol 0": configs["Newton, ftol 0"],
            "Newton, ftol 0, the iterate before its last update": dict(
                root_finder=_BeforeLastUpdate(ftol=0.0)),
        }
    if nudges is None:
        runs = [(name, options, None) for name, options in configs.items()]
    else:
        chosen = [name for name in configs
                  if name.startswith(("Newton, ftol", "Newton, exactly", "chord, ftol 0"))]
        runs = [(name, configs[name], seed) for seed in [None, *nudges] for name in chosen]
    per_finder = {}
    for name, options, seed in runs:
        solver = _bias_solver(options, seed)
        ctx = solver.step_context(*_oscillator_step(h))
        span = _span(solver, ctx)
        trajectories, histogram = rounding_bias.oscillator_runs(
            solver, steps, phases, h, m, k, amplitude=0.5)
        iterations = float(np.arange(len(histogram)) @ histogram / np.sum(histogram))
        stats = rounding_bias.bias_statistics(trajectories, span, ctx.weights, h, m, k)
        per_finder.setdefault(name, []).append(stats)
        label = "as computed" if seed is None else f"nudged, seed {seed}"
        print(f"| {name} | {label} | {stats.mean:+.2e} | {stats.se:.1e} "
              f"| {stats.mean / stats.se:+.1f} | {stats.rms:.2f} "
              f"| {stats.mean * steps * eps:+.1e} | {stats.det_change:+.2e} "
              f"| {iterations:.2f} |", flush=True)
    if nudges:
        print("\nover the spans: the mean of the spans' mean biases, its standard error (from "
              "the spans' own), and the spans whose bias is beyond 3 of their standard errors")
        print("| root finder | spans | mean over the spans | standard error | "
              "mean / standard error | spans beyond 3 SE |")
        print("|---|---|---|---|---|---|")
        for name, rows in per_finder.items():
            mean, se, beyond = over_spans(rows)
            print(f"| {name} | {len(rows)} | {mean:+.2e} | {se:.1e} | {mean / se:+.1f} "
                  f"| {beyond} |", flush=True)


def over_spans(rows) -> tuple[float, float, int]:
    """The mean of several spans' mean biases (`BiasStatistics`), its standard error (from
    the spans' own, as independent), and how many spans lie beyond 3 of their own."""
    mean = float(np.mean([r.mean for r in rows]))
    se = float(np.sqrt(np.sum([r.se**2 for r in rows])) / len(rows))
    return mean, se, sum(abs(r.mean) > 3 * r.se for r in rows)


def _oscillator_step(h: float):
    """`(term, t0, dt, y0, args)` of the oscillator's step, for `step_context`."""
    problem = problems.harmonic_oscillator()
    return problem.term, 0.0, h, problem.y0, problem.args


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--only",
                        choices=("energy", "growth", "compensation", "cost", "bias"),
                        default=None)
    parser.add_argument("--members", type=int, default=16)
    parser.add_argument("--solver", default=None, help="growth: only solvers whose name has this")
    parser.add_argument("--nudge", type=int, nargs="+", default=None, metavar="SEED",
                        help="bias: CGVI(7)'s Newton steps on spans nudged by these seeds")
    parser.add_argument("--updates", type=int, nargs="+", default=None, metavar="K",
                        help="bias: Newton with exactly K updates per step (and ftol 0)")
    args = parser.parse_args(argv)
    for n in args.updates or ():
        try:
            _FixedUpdates(updates=n)
        except ValueError as error:
            parser.error(f"--updates: {error}")
    if args.only in (None, "energy"):
        energy_growth(args.steps)
    if args.only in (None, "growth"):
        energy_growth_ensemble(args.steps, args.members, args.solver)
    if args.only in (None, "compensation"):
        compensation()
    if args.only in (None, "cost"):
        step_cost()
    if args.only in (None, "bias"):
        energy_bias(min(args.steps, 100_000), min(args.members, 4), args.nudge, args.updates)


if __name__ == "__main__":
    main()
