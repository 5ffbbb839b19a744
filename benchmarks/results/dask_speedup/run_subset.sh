#!/bin/bash
# run.sh with the CPU time of each command (its Dask workers included) and an optional
# subset of problems: OUT=/tmp/dask_speedup2 PROBLEMS=harmonic_oscillator bash benchmarks/results/dask_speedup/run_subset.sh 3
set -e
repeats=${1:-3}
out=${OUT:-/tmp/dask_speedup2}
problems=${PROBLEMS:+--problems $PROBLEMS}
mkdir -p "$out"
for i in $(seq "$repeats"); do
  for mode in serial cluster; do
    jobs=1; [ "$mode" = cluster ] && jobs=2
    /usr/bin/time -o "$out/$mode$i.time" -f "%e %U %S" .venv/bin/python -m diffrax_vi.bench \
      stability --quick $problems --jobs "$jobs" --no-progress --out "$out/$mode$i" \
      > "$out/$mode$i.log" 2>&1
    read wall user sys < "$out/$mode$i.time"
    echo "$mode run $i: $wall s wall, $(echo "$user + $sys" | bc) s CPU (load average: $(cut -d' ' -f1-3 /proc/loadavg))"
  done
done
