"""Helpers shared by more than one benchmark script.

The repository's paths, a command line that reruns a benchmark module in a fresh process,
and the arguments and adaptive diffrax runs ("peers") that `energy_drift` and `long_runs`
share.
"""

from __future__ import annotations

import argparse
import inspect
import pathlib
import shlex
import sys

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import timed  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent.parent
"""The repository root (the folder that holds `benchmarks/`)."""

RESULTS = ROOT / "benchmarks" / "results"
"""Where the tracked result files live."""


def module_command(module: str, *args: str) -> list[str]:
    """The command line that runs the benchmark module `module` (e.g. `"benchmarks.speed"`)
    with `args` in a fresh Python process; run it with `cwd=ROOT`."""
    return [sys.executable, "-m", module, *args]


def command_line(module: str, argv=None) -> str:
    """This run as `python -m <module> <arguments>`, for the header of a results file;
    `argv` is what `main` was called with (None: `sys.argv[1:]`)."""
    return shlex.join(["python", "-m", module, *(sys.argv[1:] if argv is None else argv)])


PEERS = {"tsit5": diffrax.Tsit5, "dopri8": diffrax.Dopri8}
"""The adaptive diffrax solvers that `--peers NAME:RTOL` can name."""

PROBLEM_NAMES = sorted(
    name for name in dir(problems)
    if name[0].islower() and inspect.isfunction(getattr(problems, name))
)
"""The problem constructors of `diffrax_vi.problems`, by name."""


def peer_run(name: str, rtol: float, problem, h: float, steps: int, samples: int = 1000):
    """An adaptive diffrax peer over the same span (`steps·h`), its energy sampled at
    `samples` evenly spaced times. Returns (largest relative energy error, accepted steps,
    wall seconds of the run after its compiling call, whether it reached the end)."""
    t1 = problem.t0 + steps * h
    ts = jnp.linspace(problem.t0, t1, samples + 1)[1:]
    term = problem.term.to_ode()

    @jax.jit
    def solve(y0):
        return diffrax.diffeqsolve(
            term, PEERS[name](), problem.t0, t1, h, y0, args=problem.args,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol * 1e-2),
            saveat=diffrax.SaveAt(ts=ts), max_steps=2**24, throw=False)

    sol = solve(problem.y0)
    jax.block_until_ready(sol.ys)
    sol, seconds = timed(solve, problem.y0)
    e0 = float(problem.energy(problem.t0, *problem.y0))
    energy = jax.vmap(lambda a, b: problem.energy(problem.t0, a, b))(*sol.ys)
    ok = bool(sol.result == diffrax.RESULTS.successful)
    largest = float(jnp.max(jnp.abs(energy - e0))) / abs(e0) if ok else float("inf")
    return largest, int(sol.stats["num_accepted_steps"]), seconds, ok


def parse_peer(parser: argparse.ArgumentParser, text: str) -> tuple[str, float]:
    """`NAME:RTOL` of `--peers`, checked before anything runs (a bad one ends the program
    through `parser.error`)."""
    name, _, rtol = text.partition(":")
    if name not in PEERS:
        parser.error(f"--peers: unknown peer {name!r} in {text!r}; known: {', '.join(PEERS)}")
    try:
        value = float(rtol)
    except ValueError:
        value = -1.0
    if not value > 0:
        parser.error(f"--peers: {text!r} needs a positive RTOL after the colon, e.g. {name}:1e-10")
    return name, value


def positive(kind):
    """An argparse `type` that converts with `kind` and refuses values that are not > 0."""

    def convert(text):
        value = kind(text)
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return value

    return convert


def span_parser(doc: str) -> argparse.ArgumentParser:
    """A parser with the arguments of a run over a span of fixed steps: the problem, the
    step, the number of steps (checked), and `--peers`."""
    parser = argparse.ArgumentParser(description=doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("problem", choices=PROBLEM_NAMES)
    parser.add_argument("h", type=positive(float))
    parser.add_argument("steps", type=positive(int))
    parser.add_argument("--peers", nargs="*", default=[],
                        help="adaptive diffrax peers over the same span, as NAME:RTOL "
                             "(NAME in tsit5, dopri8), e.g. dopri8:1e-12")
    return parser


def report_peers(peers, problem, h: float, steps: int, prefix: str = "\n") -> None:
    """Run and print each `--peers` entry over the span of `steps` steps of `h`."""
    for name, rtol in peers:
        largest, accepted, seconds, ok = peer_run(name, rtol, problem, h, steps)
        status = "reached the end" if ok else "did not reach the end"
        print(f"{prefix}{name} rtol {rtol}: {status}, {accepted} steps in {seconds:.2f} s "
              f"(after compiling); largest energy error at 1000 sampled times {largest:.1e}")
