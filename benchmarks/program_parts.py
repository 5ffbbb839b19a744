"""Which parts of the solver make up the compiled program of a NetworkVI `diffeqsolve`.

Compile time grows with the size of the program XLA is handed. This script traces one solve
(as `benchmarks/compile_phases.py` does, same fixtures and configurations) and counts the
primitive operations of its jaxpr, sub-programs (loop bodies, branches, jitted calls)
included, and attributes each to the innermost `diffrax_vi` function on its traceback (or to
`other` when none is); `--depth N` groups by the chain of the N outermost package functions
instead, a view from the top. Sub-programs called more than once are counted once per call site,
like the lowered program does. It prints the largest parts first.

    .venv/bin/python -m benchmarks.program_parts double_pendulum fast
"""

from __future__ import annotations

import argparse
import collections
import os

import jax

jax.config.update("jax_enable_x64", True)

from jax.extend import core as jex_core  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from benchmarks.compile_phases import NODES, fixture_solve  # noqa: E402
from benchmarks.speed import CONFIGS  # noqa: E402

PACKAGE = os.path.dirname(os.path.abspath(dvi.__file__))


def _owner(eqn, depth: int = 0) -> str:
    """`module:function` of the innermost frame inside the package (`depth` 0), or the chain
    of the `depth` outermost package frames, else `other`."""
    traceback = eqn.source_info.traceback
    frames = traceback.frames if traceback is not None else []
    names = [
        os.path.relpath(f.file_name, PACKAGE)[:-3].replace(os.sep, ".") + ":" + f.function_name
        for f in frames  # innermost first
        if f.file_name.startswith(PACKAGE)
    ]
    if not names:
        return "other"
    return names[0] if depth == 0 else " > ".join(names[::-1][:depth])


def _sub_jaxprs(eqn):
    for value in eqn.params.values():
        items = value if isinstance(value, tuple | list) else (value,)
        for item in items:
            if isinstance(item, jex_core.ClosedJaxpr):
                yield item.jaxpr
            elif isinstance(item, jex_core.Jaxpr):
                yield item


def count_parts(jaxpr, counts: collections.Counter, depth: int = 0) -> None:
    """Add the primitive operations of `jaxpr` and its sub-programs to `counts`."""
    for eqn in jaxpr.eqns:
        subs = list(_sub_jaxprs(eqn))
        if subs:
            for sub in subs:
                count_parts(sub, counts, depth)
        else:
            counts[_owner(eqn, depth)] += 1


def program_parts(problem_name: str, config: str, depth: int = 0, steps: int = 20, h=0.1):
    """Operation counts per owning function (see `_owner`) of one solve's jaxpr."""
    run, problem = fixture_solve(problem_name, config, steps=steps, h=h)
    counts: collections.Counter = collections.Counter()
    count_parts(jax.make_jaxpr(run)(problem.y0).jaxpr, counts, depth)
    return counts


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("problem", choices=sorted(NODES))
    parser.add_argument("config", choices=sorted(CONFIGS))
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--depth", type=int, default=0,
                        help="0: innermost package function; N: chain of the N outermost")
    ns = parser.parse_args(argv)
    counts = program_parts(ns.problem, ns.config, ns.depth)
    total = sum(counts.values())
    print(f"{ns.problem} {ns.config}: {total} primitive operations")
    for owner, n in counts.most_common(ns.top):
        print(f"{n:7d} {100 * n / total:5.1f} %  {owner}")


if __name__ == "__main__":
    main()
