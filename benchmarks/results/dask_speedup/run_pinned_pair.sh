#!/bin/bash
# One pair: the quick stability sweep in one process pinned to core 0, then on the two-worker
# cluster (run_pinned_pairs.sh once; its outputs are serial1 and cluster1, where the pairs
# recorded here before 2026-11-28 were named serial_one_core and cluster).
# Run from the repository root: OUT=/tmp/dask_speedup4 bash benchmarks/results/dask_speedup/run_pinned_pair.sh
OUT=${OUT:-/tmp/dask_speedup4} exec bash "$(dirname "$0")/run_pinned_pairs.sh" 1
