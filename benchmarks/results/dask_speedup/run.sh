#!/bin/bash
# The quick stability sweep in one unpinned process (--jobs 1) and on the embedded two-worker
# Dask cluster (--jobs 2, one pinned worker per core), interleaved REPEATS times; wall and CPU
# time of each command, then the tables compared case by case (run_pinned_pairs.sh with the
# serial process unpinned).
# Run from the repository root: bash benchmarks/results/dask_speedup/run.sh [REPEATS]
OUT=${OUT:-/tmp/dask_speedup} SERIAL_CPUS= exec bash "$(dirname "$0")/run_pinned_pairs.sh" "${1:-3}"
