#!/bin/bash
# run.sh on a subset of the problems:
#   OUT=/tmp/dask_speedup2 PROBLEMS=harmonic_oscillator bash benchmarks/results/dask_speedup/run_subset.sh 3
OUT=${OUT:-/tmp/dask_speedup2} SERIAL_CPUS= exec bash "$(dirname "$0")/run_pinned_pairs.sh" "${1:-3}"
