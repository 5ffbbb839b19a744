"""The explicit symplectic solvers against Dopri8 and heyoka (where importable) on Kepler.

Two measurements, in one process:

- **fronts**: Kepler e = 0.5 over ten orbits. For each tolerance `rtol = atol` of Dopri8
  (PIDController) its final-state error is the target; each explicit method takes the fewest
  constant steps (on a grid of ratio 1.1) that reach an error at most the target, and both are
  timed side by side (best of `--repeats`), once alone and once under `jax.vmap` over
  `--members` rotated copies of the orbit (the same orbit, so the same errors). Where heyoka
  is importable (`diffrax_vi.bench.peers`) it runs in the same process: its tolerance swept
  over a grid of ratio 10^(1/4) from 1e-6 to 1e-16, for each target the fastest tolerance whose
  error is at most the target, alone (one `propagate_until`) and for the members (heyoka's
  SIMD batch mode, `taylor_adaptive_batch`, one core, looped over chunks of its width; the
  batch's own error must meet the target too). Printed: each method's steps, error and time,
  the ratios to Dopri8, and the ratios of the fastest explicit method to Dopri8 and to heyoka.
- **energy**: the energy error over 10⁶ constant Kepler steps of each order, the largest
  `|H − H₀|` over the first and over the last tenth of the run (bounded: the last tenth's
  within 3x the first's).

    .venv/bin/python -m benchmarks.explicit_methods [--only fronts|energy] [--repeats 5]
"""

from __future__ import annotations

import argparse
import math
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi.bench.peers import heyoka_available  # noqa: E402

ORBITS = 10
TOLERANCES = (1e-10, 1e-12, 1e-13)
MAX_STEPS = 400_000
METHODS = {
    "StormerVerlet": dvi.StormerVerlet(),
    "Composition(4, suzuki)": dvi.Composition(4, "suzuki"),
    "Composition(6, kahan_li)": dvi.Composition(6, "kahan_li"),
    "Composition(6, suzuki)": dvi.Composition(6, "suzuki"),
    "Composition(8, kahan_li)": dvi.Composition(8, "kahan_li"),
    "Composition(8, triple_jump)": dvi.Composition(8, "triple_jump"),
    "BlanesMoan(4)": dvi.BlanesMoan(4),
    "BlanesMoan(6)": dvi.BlanesMoan(6),
}
# Not explicit: the variational solver of the same package, for the choosing page
# (`--methods "CGVI(6)"`); never counted as "the fastest explicit method".
OTHERS = {"CGVI(4)": lambda: dvi.CGVI(4), "CGVI(6)": lambda: dvi.CGVI(6)}


def rotated_members(y0, members: int):
    """`members` copies of the state rotated by angles spread over the circle."""
    angles = np.linspace(0, 2 * np.pi, members, endpoint=False)
    c, s = np.cos(angles), np.sin(angles)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (members, 2, 2)
    return tuple(jnp.asarray(np.einsum("mij,j->mi", rot, np.asarray(x))) for x in y0), rot


def best_of(fn, repeats: int) -> float:
    jax.block_until_ready(fn())  # compiled and warm
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times)


def _final(sol):
    return sol.ys[0][-1], sol.ys[1][-1]


def dopri8_program(problem, tol: float):
    t0, t1 = jnp.asarray(problem.t0), jnp.asarray(problem.t1)

    def run(y0):
        return _final(diffrax.diffeqsolve(
            problem.term, diffrax.Dopri8(), t0, t1, 0.01, y0, max_steps=MAX_STEPS,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol)))

    return run


def explicit_program(problem, solver):
    t0, t1 = jnp.asarray(problem.t0), jnp.asarray(problem.t1)

    def run(n, y0):
        return _final(diffrax.diffeqsolve(problem.term, solver, t0, t1, (t1 - t0) / n, y0,
                                          max_steps=MAX_STEPS))

    return run


def state_error(y, reference) -> float:
    return float(max(np.max(np.abs(np.asarray(a) - b)) for a, b in zip(y, reference,
                                                                        strict=True)))


def steps_for(program, problem, reference, targets, start=16):
    """For each target, the fewest steps on a grid of ratio 1.1 whose error is at most it
    (`None` past `MAX_STEPS`), and that error."""
    run = jax.jit(program)
    found = {}
    n = start
    while len(found) < len(targets) and n <= MAX_STEPS:
        try:
            err = state_error(run(n, problem.y0), reference)
        except Exception:  # an implicit solver's step failed: too long a step
            err = math.inf
        for target in targets:
            if target not in found and err <= target:
                found[target] = (n, err)
        n = max(n + 1, int(n * 1.1))
    return {t: found.get(t, (None, math.nan)) for t in targets}


# heyoka's tolerances: a grid of ratio 10^(1/4) from 1e-6 to 1e-16 (its error is not
# monotonic in the tolerance near round-off, so every point is measured).
HEYOKA_TOLERANCES = tuple(10.0 ** (-k / 4) for k in range(24, 65))


def heyoka_front(problem, reference, batch, batch_reference, targets, repeats: int):
    """heyoka at each target error: `{target: (alone, members)}`, each `None` where no
    tolerance of `HEYOKA_TOLERANCES` reaches the target, else `(tol, order, steps, error,
    seconds)` of the fastest tolerance whose error is at most the target — alone one
    `propagate_until` (best of `repeats`), for the members the SIMD batch mode looped over
    chunks of its width (best of `repeats`, its error over all members). Also returns the
    sweep's points `(tol, order, steps, error, alone_s, batch_error, batch_s)`."""
    from diffrax_vi.bench.peers import HeyokaPeer

    y0s = np.concatenate([np.asarray(x) for x in batch], axis=1)  # members × (q, p)
    d = problem.dim
    points = []
    for tol in HEYOKA_TOLERANCES:
        # heyoka's caches of compiled code left on: its build is not what is timed here
        peer = HeyokaPeer(problem, tol, cold_compile=False)
        run = peer.timed_run(repeats=repeats, reference=reference)
        if run.outcome != "time_limit" or not run.state_error <= max(targets):
            points.append((tol, peer.order, run.steps, run.state_error, run.wall_s, math.nan,
                           math.nan))
            continue
        many = peer.propagate_many(y0s, float(problem.t1), method="batch", repeats=repeats)
        batch_err = state_error((many.states[:, :d], many.states[:, d:]), batch_reference)
        points.append((tol, peer.order, run.steps, run.state_error, run.wall_s, batch_err,
                       many.wall_s))
    # Neighbouring tolerances often give heyoka the same order and the same steps, hence the
    # same run: one configuration, represented by its largest tolerance, timed by the best of
    # all its runs (otherwise the choice among equal runs is the timer's noise).
    same: dict[tuple, list] = {}
    for p in points:
        same.setdefault((p[1], p[2], p[3], p[5]), []).append(p)
    merged = [(max(g, key=lambda p: p[0])[0], *g[0][1:4], min(p[4] for p in g), g[0][5],
               min(p[6] for p in g)) for g in same.values()]
    found = {}
    for target in targets:
        alone = [p for p in merged if p[3] <= target]
        members = [p for p in merged if p[5] <= target]
        found[target] = (min(alone, key=lambda p: p[4]) if alone else None,
                         min(members, key=lambda p: p[6]) if members else None)
    return found, points


def fronts(repeats: int, members: int, names=None) -> None:
    problem = dvi.problems.kepler(0.5, t1=2 * math.pi * ORBITS)
    qr, pr = problem.reference(np.array([problem.t1]))
    reference = (qr[-1], pr[-1])
    batch, rot = rotated_members(problem.y0, members)
    batch_reference = tuple(np.einsum("mij,j->mi", rot, r) for r in reference)
    print(f"Kepler e = 0.5, {ORBITS} orbits; errors max |state - exact| at t1; wall time best "
          f"of {repeats}; vmap over {members} rotated copies (heyoka's rows: its batch mode "
          f"over the same {members} copies in the vmap columns); ratios to Dopri8")
    targets, dopri = {}, {}
    for tol in TOLERANCES:
        run = jax.jit(dopri8_program(problem, tol))
        batched = jax.jit(jax.vmap(run))
        err = state_error(run(problem.y0), reference)
        targets[tol] = err
        dopri[tol] = (err, best_of(lambda run=run: run(problem.y0), repeats),
                      best_of(lambda b=batched: b(batch), repeats))
        print(f"Dopri8 rtol={tol:g}: error {err:.2e}, alone {dopri[tol][1] * 1e3:.2f} ms, "
              f"vmap {dopri[tol][2] * 1e3:.1f} ms")
    heyoka = None
    if heyoka_available():
        heyoka, points = heyoka_front(problem, reference, batch, batch_reference,
                                      list(targets.values()), repeats)
        print(f"heyoka (float64, tolerances 1e-6..1e-16 by 10^(1/4); members: batch mode of "
              f"SIMD width {_simd_width()}, one core): error against the tolerance")
        for tol, order, steps, err, alone, batch_err, many in points:
            extra = "" if math.isnan(many) else \
                f", members error {batch_err:.2e} in {many * 1e3:.1f} ms"
            print(f"  tol={tol:.2e} order {order:2d} {steps:4d} steps: error {err:.2e}, "
                  f"alone {alone * 1e3:.3f} ms{extra}")
    else:
        print("heyoka: not importable here (pip install heyoka to add it)")
    rows = {tol: [] for tol in TOLERANCES}
    chosen = {**METHODS, **{k: f() for k, f in OTHERS.items()}} if names else METHODS
    for name, solver in chosen.items():
        if names and name not in names:
            continue
        program = explicit_program(problem, solver)
        found = steps_for(program, problem, reference, [targets[t] for t in TOLERANCES],
                          start=16 if name in METHODS else 32 * ORBITS)
        run = jax.jit(program)
        batched = jax.jit(jax.vmap(program, in_axes=(None, 0)))
        for tol in TOLERANCES:
            n, err = found[targets[tol]]
            if n is None:
                print(f"  {name}: no step count up to {MAX_STEPS} reaches {targets[tol]:.2e}")
                continue
            alone = best_of(lambda run=run, n=n: run(n, problem.y0), repeats)
            vm = best_of(lambda b=batched, n=n: b(n, batch), repeats)
            vm_err = state_error(batched(n, batch), batch_reference)
            rows[tol].append((name, n, err, vm_err, alone, vm))
    for tol in TOLERANCES:
        err, alone, vm = dopri[tol]
        print(f"\nat Dopri8 rtol={tol:g} (error {err:.2e}, {alone * 1e3:.2f} ms alone, "
              f"{vm * 1e3:.1f} ms vmap):")
        print(f"  {'method':30s} {'steps':>7s} {'error':>9s} {'vmap err':>9s} "
              f"{'alone ms':>9s} {'ratio':>6s} {'vmap ms':>9s} {'ratio':>6s}")
        table = list(rows[tol])
        if heyoka is not None:
            chosen_points = {p[0]: p for p in heyoka[err] if p is not None}
            for p_tol, order, steps, e, a, ve, v in chosen_points.values():
                table.append((f"heyoka(tol={p_tol:.1e}, order {order})", steps, e, ve, a, v))
        for name, n, e, ve, a, v in sorted(table, key=lambda r: r[4]):
            print(f"  {name:30s} {n:7d} {e:9.2e} {ve:9.2e} {a * 1e3:9.2f} {a / alone:6.3f} "
                  f"{v * 1e3:9.1f} {v / vm:6.3f}")
        explicit = [r for r in rows[tol] if r[0] in METHODS]
        if explicit:
            fast = min(explicit, key=lambda r: r[4])
            fast_vm = min(explicit, key=lambda r: r[5])
            print(f"  fastest alone: {fast[0]} at {fast[4] / alone:.3f}x Dopri8's time; "
                  f"fastest under vmap: {fast_vm[0]} at {fast_vm[5] / vm:.3f}x")
        if heyoka is None:
            continue
        h_alone, h_many = heyoka[err]
        for what, point in (("alone", h_alone), ("members", h_many)):
            if point is None:
                print(f"  heyoka {what}: no tolerance down to 1e-16 reaches {err:.2e}")
                continue
            p_tol, order, _, e, a, ve, v = point
            print(f"  heyoka fastest {what}: tol={p_tol:.1e} (order {order}), error "
                  f"{e if what == 'alone' else ve:.2e}, "
                  + (f"{a * 1e3:.3f} ms alone, {a / alone:.4f}x Dopri8" if what == "alone"
                     else f"{v * 1e3:.2f} ms for {members} members, {v / vm:.4f}x Dopri8"))
        if explicit and h_alone is not None and h_many is not None:
            print(f"  fastest explicit / heyoka: alone {fast[4] / h_alone[4]:.1f}x "
                  f"({fast[0]}), {members} members {fast_vm[5] / h_many[6]:.2f}x "
                  f"({fast_vm[0]} under vmap against heyoka's batch mode)")


def _simd_width() -> int:
    from diffrax_vi.bench.peers import require_heyoka

    return int(require_heyoka().recommended_simd_size())


def energy_growth(solver, h: float, steps: int, problem=None) -> tuple[float, float]:
    """`(max |ΔH| over the first tenth, over the last tenth)` of `steps` constant Kepler steps
    of `solver` (stepped by hand inside one compiled loop)."""
    problem = dvi.problems.kepler(0.5) if problem is None else problem
    term = problem.term
    energy = eqx.filter_jit(lambda y: 0.5 * y[1] @ y[1] - 1 / jnp.sqrt(y[0] @ y[0]))
    chunk = steps // 10

    @jax.jit
    def tenths(y0):
        state = solver.init(term, 0.0, h, y0, None)
        e0 = energy(y0)

        def one(carry, k):
            def body(i, c):
                y, s, worst = c
                t = (k * chunk + i) * h
                y, _, _, s, _ = solver.step(term, t, t + h, y, None, s, False)
                return y, s, jnp.maximum(worst, jnp.abs(energy(y) - e0))

            y, s, worst = jax.lax.fori_loop(0, chunk, body, (*carry, 0.0))
            return (y, s), worst

        return jax.lax.scan(one, (y0, state), jnp.arange(10))[1]

    worst = np.asarray(tenths(problem.y0))
    return float(worst[0]), float(worst[-1])


ENERGY_RUNS = (
    (dvi.StormerVerlet(), 0.01), (dvi.Composition(4), 0.05), (dvi.BlanesMoan(4), 0.05),
    (dvi.Composition(6), 0.1), (dvi.BlanesMoan(6), 0.1), (dvi.Composition(8), 0.1),
)


def energy() -> None:
    print("\nKepler e = 0.5, 10^6 constant steps: max |H - H0| over the first and last tenth")
    for solver, h in ENERGY_RUNS:
        start = time.perf_counter()
        first, last = energy_growth(solver, h, 1_000_000)
        name = f"{type(solver).__name__}(order {solver.order(None)})"
        print(f"  {name:26s} h={h:<5g} first {first:.3e} last {last:.3e} "
              f"ratio {last / first:.2f} ({time.perf_counter() - start:.1f} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=("fronts", "energy"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--members", type=int, default=256)
    parser.add_argument("--methods", nargs="+", metavar="NAME",
                        help=f"only these of {list(METHODS) + list(OTHERS)}")
    args = parser.parse_args()
    if args.only in (None, "fronts"):
        fronts(args.repeats, args.members, args.methods)
    if args.only in (None, "energy"):
        energy()


if __name__ == "__main__":
    main()
