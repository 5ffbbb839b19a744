"""Cost of one step of `NetworkVI`, per seed strategy, next to diffrax's adaptive `Tsit5`.

Problem: the harmonic oscillator in float64, N fixed steps of h = 0.1 (t1 = N h). Solver:
`NetworkVI(ShallowNetBasis(tanh, 10), GaussLegendre(8))` seeded either by
`IntegratorExtrapolation()` (midpoint sub-integration + OGA fit on every step, the default) or
by `PreviousStep()` (warm start from the previous step's network). The peer is `Tsit5()` with
`PIDController(rtol=1e-10, atol=1e-12)` on the same term.

Each solver runs inside one `eqx.filter_jit`-ed `diffeqsolve(..., throw=False)` and reports:

- compile s: wall time of the first call minus one steady-state run;
- total ms: median steady-state run time over the repeats;
- per step: total / steps taken (N for a successful fixed-step run; accepted steps for Tsit5);
- iterations per step (NetworkVI): median (from the solver state's histogram), mean, max;
- the diffrax result, the time t_end the solve reached (t1 unless it failed), and the error of
  q there relative to the oscillation amplitude, `max|q(t_end) - q_ref(t_end)| / max_t |q_ref|`
  (q_ref(t1) itself may sit near a zero crossing, e.g. for t1 = 100).

A solver that fails still gets its row. Run it with

    .venv/bin/python -m benchmarks.step_cost [--steps 1000] [--repeats 5] [--dict-amount K]
    .venv/bin/python -m benchmarks.step_cost --quick      # 100 steps, 3 repeats
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.common import command_line  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import iteration_summary, timed  # noqa: E402

H = 0.1


def measure(problem, solver, repeats, **solve_kwargs) -> dict:
    """Compile once, time `repeats` steady-state runs, and read the final state and result."""

    @eqx.filter_jit
    def run(y0):
        return diffrax.diffeqsolve(
            problem.term,
            solver,
            problem.t0,
            problem.t1,
            H,
            y0,
            args=problem.args,
            saveat=diffrax.SaveAt(t1=True, solver_state=True),
            throw=False,
            **solve_kwargs,
        )

    sol, first_s = timed(run, problem.y0)
    total_s = statistics.median(timed(run, problem.y0)[1] for _ in range(repeats))

    ok = bool(sol.result == diffrax.RESULTS.successful)
    t_end = float(sol.ts[-1])  # t1, or where a failed solve stopped
    amplitude = np.max(np.abs(problem.reference(problem.ts)[0]))
    q_end = np.asarray(sol.ys[0][-1])
    row = dict(
        result="success" if ok else "FAILED: " + diffrax.RESULTS[sol.result].replace("\n", " "),
        t_end=t_end,
        compile_s=first_s - total_s,
        total_s=total_s,
        error=float(np.max(np.abs(q_end - problem.reference(t_end)[0][0])) / amplitude),
    )
    state = sol.solver_state
    if isinstance(state, dvi.NetworkVIState):
        its = iteration_summary(state)
        steps = its["steps"]
        row.update(its, steps=str(steps), warm=int(state.warm_starts))
    else:
        steps = int(sol.stats["num_accepted_steps"])
        row["steps"] = f"{steps} (+{int(sol.stats['num_rejected_steps'])} rej.)"
    row["per_step_s"] = total_s / steps if steps else None
    return row


def fmt(x, spec, scale=1):
    return "–" if x is None else format(scale * x, spec)


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=1000, help="N steps of h = 0.1")
    parser.add_argument("--repeats", type=int, default=5, help="steady-state runs to time")
    parser.add_argument("--quick", action="store_true", help="100 steps and 3 repeats")
    parser.add_argument(
        "--dict-amount", type=int, default=None, help="OGA dictionary size (default: solver's)"
    )
    args = parser.parse_args()
    if args.quick:
        args.steps, args.repeats = 100, 3
    n = args.steps

    problem = problems.harmonic_oscillator(dtype=jnp.float64).with_span(n_steps=n, dt=H)
    guess = dvi.OGA1d() if args.dict_amount is None else dvi.OGA1d(dict_amount=args.dict_amount)
    basis = dvi.ShallowNetBasis(dvi.tanh, 10)
    cases = [
        ("NetworkVI", "IntegratorExtrapolation (OGA)", dvi.IntegratorExtrapolation()),
        ("NetworkVI", "PreviousStep (warm)", dvi.PreviousStep()),
    ]
    runs = [
        (
            name,
            seed,
            dvi.NetworkVI(basis, dvi.GaussLegendre(8),
                          seed=dvi.SeedPolicy(initial_trajectory=s, initial_guess=guess)),
            dict(max_steps=n + 1),
        )
        for name, seed, s in cases
    ]
    pid = diffrax.PIDController(rtol=1e-10, atol=1e-12)
    runs.append(
        (
            "Tsit5",
            "PID rtol 1e-10, atol 1e-12",
            diffrax.Tsit5(),
            dict(stepsize_controller=pid, max_steps=1_000_000),
        )
    )

    print(f"command: {command_line('benchmarks.step_cost')}")
    print(
        f"machine: {platform.platform()}, {platform.machine()}, python {platform.python_version()}"
        f", jax {jax.__version__} ({jax.default_backend()}: {jax.devices()[0].device_kind})"
        f", diffrax {diffrax.__version__}, os.cpu_count() = {os.cpu_count()}"
    )
    print(
        f"problem: harmonic oscillator, float64, N = {n} steps of h = {H} (t1 = {problem.t1:g}),"
        f" {args.repeats} repeats; NetworkVI: ShallowNetBasis(tanh, 10), GaussLegendre(8),"
        f" dict_amount = {runs[0][2].seed.initial_guess.dict_amount}\n"
    )

    rows = []
    for name, seed, solver, kwargs in runs:
        try:
            row = measure(problem, solver, args.repeats, **kwargs)
        except Exception as e:  # a crash is reported like a failed solve
            row = dict(result=f"ERROR: {type(e).__name__}: {str(e).splitlines()[0][:80]}")
        rows.append(dict(solver=name, seed=seed, **row))

    print(
        "| solver | seed / control | result | t end | steps | compile s | total ms | ms/step "
        "| iters median | iters mean | iters max | warm starts | rel. error q(t end) |"
    )
    print("|" + "---|" * 13)
    for r in rows:
        print(
            f"| {r['solver']} | {r['seed']} | {r['result']} | {fmt(r.get('t_end'), 'g')} "
            f"| {r.get('steps', '–')} "
            f"| {fmt(r.get('compile_s'), '.2f')} | {fmt(r.get('total_s'), '.1f', 1e3)} "
            f"| {fmt(r.get('per_step_s'), '.4f', 1e3)} | {fmt(r.get('it_median'), 'd')} "
            f"| {fmt(r.get('it_mean'), '.2f')} | {fmt(r.get('it_max'), 'd')} "
            f"| {fmt(r.get('warm'), 'd')} | {fmt(r.get('error'), '.2e')} |"
        )

    def ratio(a, b, key):
        x, y = rows[a].get(key), rows[b].get(key)
        if not (x and y):
            return "–"
        failed = any(rows[i]["result"] != "success" for i in (a, b))
        return f"{x / y:.2f}x" + (" (failed run)" if failed else "")

    print("\nratios:")
    print(
        f"- PreviousStep / OGA seed: time per step {ratio(1, 0, 'per_step_s')}, "
        f"total {ratio(1, 0, 'total_s')}, compile {ratio(1, 0, 'compile_s')}"
    )
    for i in (0, 1):
        print(
            f"- {rows[i]['seed']} / Tsit5: time per step {ratio(i, 2, 'per_step_s')}, "
            f"total {ratio(i, 2, 'total_s')}, compile {ratio(i, 2, 'compile_s')}"
        )


if __name__ == "__main__":
    main()
