"""The harness's rows as CSV: `write_rows` and `read_rows`."""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

__all__ = ["COLUMNS", "read_rows", "write_rows"]

COLUMNS = (
    "problem", "solver", "family", "parameter", "value", "status", "steps", "rejected",
    "t_end", "error", "energy_error", "wall_s", "compile_s", "repeats", "iterations",
    "max_step_iterations", "nfev", "horizon", "t", "message",
)


def write_rows(rows: Iterable[Mapping[str, Any]], path, *, append: bool = False,
               columns: Sequence[str] | None = None) -> None:
    """Write rows to a CSV (header written when the file is new or not appending)."""
    import os

    rows = list(rows)
    if columns is None:
        columns = list(COLUMNS)
        for r in rows:
            columns += [k for k in r if k not in columns]
    new = not append or not os.path.exists(path) or os.path.getsize(path) == 0
    if not new:  # keep the existing header's order
        with open(path, newline="") as f:
            header = next(csv.reader(f), None)
        if header:
            columns = header
    with open(path, "a" if append else "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        if new:
            writer.writeheader()
        for r in rows:
            writer.writerow({k: ("" if v is None else v) for k, v in r.items()})
        f.flush()


def read_rows(path) -> list[dict[str, Any]]:
    """Read a CSV written by `write_rows`, turning numeric fields back into numbers."""

    def convert(v: str):
        if v == "":
            return None
        try:
            x = float(v)
        except ValueError:
            return v
        return int(x) if x.is_integer() and "." not in v and "e" not in v.lower() else x

    with open(path, newline="") as f:
        return [{k: convert(v) for k, v in r.items()} for r in csv.DictReader(f)]
