#!/bin/bash
# One process pinned to one core (taskset -c 0), then the two-worker cluster (one pinned worker
# per core): the quick stability sweep, wall and CPU time of each command.
# Run from the repository root: OUT=/tmp/dask_speedup4 bash benchmarks/results/dask_speedup/run_pinned_pair.sh
set -e
out=${OUT:-/tmp/dask_speedup4}
mkdir -p "$out"
for mode in serial_one_core cluster; do
  if [ "$mode" = cluster ]; then cmd=(.venv/bin/python); jobs=2; else cmd=(taskset -c 0 .venv/bin/python); jobs=1; fi
  /usr/bin/time -o "$out/$mode.time" -f "%e %U %S" "${cmd[@]}" -m diffrax_vi.bench \
    stability --quick --jobs "$jobs" --no-progress --out "$out/$mode" > "$out/$mode.log" 2>&1
  read wall user sys < "$out/$mode.time"
  echo "$mode: $wall s wall, $(echo "$user + $sys" | bc) s CPU (load average: $(cut -d' ' -f1-3 /proc/loadavg))"
done
