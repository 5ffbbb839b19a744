"""Where a step's solve ends at its residual floor, and what that does to the accuracy.

The default `LevenbergMarquardt` ends a step either at `ftol` or by one of its floor tests
(`diffrax_vi.nonlinear.default_tolerances`). Which floor point an iteration reaches depends on
rounding, so the error of a 10-step fixture can differ between processors by more than its
truncation error. This script solves six fixtures (10 steps of h = 0.1, float64) and prints,
per fixture, success, the largest relative error of q over the step ends and the iterations
(total and largest per step), for one root-finder setting per run:

- `--root-finder KEY=VALUE ...`: public `LevenbergMarquardt` arguments (`lam=1e-2`,
  `jacobian='auto'`, `patience_floor=20`, ...), values as Python literals;
- `--tolerance NAME=EXPONENT ...`: a default tolerance replaced by `eps**EXPONENT`
  (`floor_moving=0.75`, `otol_slow=0.875`): an experiment on the floor tests themselves,
  which patches `default_tolerances` for this process only;
- `--trace`: every iteration of the oscillator fixture (tanh width 10, Gauss–Legendre 8):
  residual `max|F|`, output change, iterations without the residual halving, failed line
  searches; the step boundary shows as an output change near 1e-7.

    .venv/bin/python -m benchmarks.floor_acceptance
    .venv/bin/python -m benchmarks.floor_acceptance --root-finder "jacobian='auto'"
    .venv/bin/python -m benchmarks.floor_acceptance --tolerance floor_moving=0.75
    .venv/bin/python -m benchmarks.floor_acceptance --trace --only 0
"""

from __future__ import annotations

import argparse
import ast

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
import diffrax_vi.nonlinear as nonlinear  # noqa: E402
from benchmarks.common import command_line  # noqa: E402
from diffrax_vi import problems  # noqa: E402

# (problem factory, its keyword arguments, activation, width, Gauss–Legendre nodes)
FIXTURES = [
    ("harmonic_oscillator", {}, dvi.tanh, 10, 8),
    ("harmonic_oscillator", {}, dvi.relu_k(3), 4, 8),
    ("double_pendulum", dict(t1=1.0, dt=0.1), dvi.tanh, 10, 16),
    ("pendulum", {}, dvi.gelu, 8, 8),
    ("harmonic_oscillator", {}, dvi.gelu, 10, 8),
    ("double_pendulum", dict(t1=1.0, dt=0.1), dvi.gelu, 10, 16),
]


class TracedLevenbergMarquardt(dvi.LevenbergMarquardt):
    """`LevenbergMarquardt` that prints its state after every iteration (a diagnostic)."""

    def step(self, fn, y, args, options, state, tags):
        y, state, aux = super().step(fn, y, args, options, state, tags)
        jax.debug.print(
            "  max|F| {f:.3e}  output change {o:.3e}  not halved for {i}  failed searches {s}",
            f=jnp.max(jnp.abs(state.f)), o=state.out_change, i=state.idle, s=state.stalls,
        )
        return y, state, aux


def key_values(items: list[str], what: str) -> dict:
    """`["a=1", "b='x'"]` -> `{"a": 1, "b": "x"}`, refusing anything else by name."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise SystemExit(f"{what}: expected NAME=VALUE, got {item!r}")
        try:
            out[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            raise SystemExit(f"{what}: {key}'s value {value!r} is not a Python literal") from None
    return out


def patch_tolerances(exponents: dict) -> None:
    """Replace default tolerances by `eps**exponent` in this process."""
    original = nonlinear.default_tolerances
    unknown = set(exponents) - set(original(jnp.float64))
    if unknown:
        raise SystemExit(f"--tolerance: unknown tolerance(s) {sorted(unknown)}; "
                         f"known: {sorted(original(jnp.float64))}")

    def patched(dtype):
        tol = original(dtype)
        eps = float(jnp.finfo(dtype).eps)
        tol.update({name: eps ** float(e) for name, e in exponents.items()})
        return tol

    nonlinear.default_tolerances = patched


def run_fixture(index: int, root_finder: dvi.LevenbergMarquardt) -> dict:
    """Solve fixture `index` with `root_finder`; success, max relative error, iterations."""
    name, kwargs, activation, width, nodes = FIXTURES[index]
    problem = getattr(problems, name)(**kwargs)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(activation, width), dvi.GaussLegendre(nodes),
                           root_finder=root_finder)
    ts = jnp.asarray(problem.ts)
    sol = diffrax.diffeqsolve(
        problem.term, solver, problem.t0, problem.t1, problem.dt, problem.y0, args=problem.args,
        saveat=diffrax.SaveAt(ts=ts, solver_state=True), throw=False,
    )
    ok = bool(sol.result == diffrax.RESULTS.successful)
    q_ref, _ = problem.reference(np.asarray(ts))
    q = np.asarray(ravel_pytree(sol.ys[0])[0]).reshape(q_ref.shape)
    error = np.max(np.abs(q - q_ref), axis=1) / np.max(np.abs(q_ref), axis=1)
    state = sol.solver_state
    return dict(
        fixture=f"{name}, {dvi.activations.activation_name(activation)} {width}, GL{nodes}",
        ok=ok, error=float(np.max(error)) if ok else float("nan"),
        iterations=int(state.iterations), max_iterations=int(state.max_iterations),
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root-finder", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--tolerance", nargs="*", default=[], metavar="NAME=EXPONENT")
    parser.add_argument("--trace", action="store_true", help="print every iteration")
    parser.add_argument("--only", type=int, nargs="*", choices=range(len(FIXTURES)),
                        help="fixture indices (default: all)")
    args = parser.parse_args(argv)
    options = key_values(args.root_finder, "--root-finder")
    exponents = key_values(args.tolerance, "--tolerance")
    kind = TracedLevenbergMarquardt if args.trace else dvi.LevenbergMarquardt
    try:
        root_finder = kind(**options)
    except (TypeError, ValueError) as err:
        raise SystemExit(f"--root-finder: {err}") from None
    if exponents:
        patch_tolerances(exponents)
    print(f"command: {command_line('benchmarks.floor_acceptance', argv)}")
    print("| fixture (10 steps, h = 0.1) | ok | max rel. error of q | iterations | max per step |")
    print("|---|---|---|---|---|")
    for index in range(len(FIXTURES)) if args.only is None else args.only:
        r = run_fixture(index, root_finder)
        print(f"| {r['fixture']} | {r['ok']} | {r['error']:.3e} | {r['iterations']} "
              f"| {r['max_iterations']} |", flush=True)


if __name__ == "__main__":
    main()
