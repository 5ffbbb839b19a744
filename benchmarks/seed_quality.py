"""Seed quality of every OGA configuration, without an integrator (see
`diffrax_vi.bench.seed_quality` for the cases and the scores).

    python -m benchmarks.seed_quality                 # whole grid: 6048 cases + presets
    python -m benchmarks.seed_quality --quick         # grid1d and angular dictionaries only
    python -m benchmarks.seed_quality --out /tmp/sq   # default: benchmarks/results/seed_quality

Writes `<out>.csv` (one row per case) and `<out>.md` (summary tables, and the time of one
jitted fit with a 50000-interval dictionary), and prints the markdown.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

from benchmarks.common import RESULTS  # noqa: E402
from diffrax_vi.bench import seed_quality as sq  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(RESULTS / "seed_quality"))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--precisions", default=",".join(sq.PRECISIONS))
    args = parser.parse_args()
    configs = sq.study_configs()
    if args.quick:
        configs = [c for c in configs if c[1] in ("grid1d", "angular")]
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    cases = sq.run_study(
        args.precisions.split(","), configs, progress=lambda m: print(m, file=sys.stderr)
    )
    elapsed = time.perf_counter() - start
    timing = sq.time_large_dictionary()
    report = sq.summary_markdown(cases) + (
        f"\n### One jitted fit, 50000-interval dictionary\n\n"
        f"OGA1d, tanh, width {10}, 11 nodes, float64, {timing['atoms']} atoms: "
        f"compile {timing['compile_s']:.1f} s, median {timing['single_ms']:.2f} ms per fit; "
        f"{timing['batch']} targets under one vmap {timing['vmap_ms']:.2f} ms "
        f"(a Python loop of single fits: {timing['loop_ms']:.2f} ms).\n"
        f"\nStudy wall time {elapsed:.0f} s (jax {jax.__version__}, {jax.default_backend()}).\n"
    )
    sq.write_csv(cases, out.with_suffix(".csv"))
    out.with_suffix(".md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
