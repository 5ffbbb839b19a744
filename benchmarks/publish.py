"""Produce the published benchmark results: run the studies of `diffrax_vi.bench` and copy the
figures to `docs/assets/benchmarks/` for `docs/benchmarks.md`.

    .venv/bin/python -m benchmarks.publish --quick          # = make bench-quick, then copy
    .venv/bin/python -m benchmarks.publish --full           # hours
    .venv/bin/python -m benchmarks.publish --copy-only      # only copy existing figures

Any other option is passed to `python -m diffrax_vi.bench` (e.g. `--problems kepler`).
"""

from __future__ import annotations

import argparse
import os
import shutil

from diffrax_vi.bench.__main__ import main as bench_main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIGURES = ("work_precision.png", "long_time_energy.png", "stability_heatmap.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true")
    mode.add_argument("--full", action="store_true")
    parser.add_argument("--copy-only", action="store_true")
    args, rest = parser.parse_known_args()
    full = args.full
    out = os.path.join(ROOT, "benchmarks", "results-full" if full else "results")
    if not args.copy_only:
        bench_main(["all", "--full" if full else "--quick", "--out", out, *rest])
    target = os.path.join(ROOT, "docs", "assets", "benchmarks")
    os.makedirs(target, exist_ok=True)
    for name in FIGURES:
        source = os.path.join(out, name)
        if os.path.exists(source):
            stem, ext = os.path.splitext(name)
            shutil.copy(source, os.path.join(target, f"{stem}{'_full' if full else ''}{ext}"))
            print("copied", source)


if __name__ == "__main__":
    main()
