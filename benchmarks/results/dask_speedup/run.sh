#!/bin/bash
# The quick stability sweep (216 cases, 36 compilations) in one process (--jobs 1) and on the
# embedded two-worker Dask cluster (--jobs 2, one pinned worker per core), interleaved
# (serial, cluster, serial, cluster, ...); wall time of the whole command, cluster start-up
# and the workers' imports included. Then the two tables compared case by case.
# Run from the repository root: bash benchmarks/results/dask_speedup/run.sh [REPEATS]
set -e
repeats=${1:-3}
out=${OUT:-/tmp/dask_speedup}
mkdir -p "$out"
for i in $(seq "$repeats"); do
  for mode in serial cluster; do
    jobs=1; [ "$mode" = cluster ] && jobs=2
    start=$(date +%s.%N)
    .venv/bin/python -m diffrax_vi.bench stability --quick --jobs "$jobs" --no-progress \
      --out "$out/$mode$i" > "$out/$mode$i.log" 2>&1
    end=$(date +%s.%N)
    echo "$mode run $i: $(echo "$end - $start" | bc) s (load average: $(cut -d' ' -f1-3 /proc/loadavg))"
  done
done
.venv/bin/python - "$out" "$repeats" <<'PY'
import csv, statistics, sys
out, repeats = sys.argv[1], int(sys.argv[2])
def table(path):
    with open(path) as f:
        return sorted((r["problem"], r["dtype"], r["activation"], r["solver"], r["acceptance"],
                       r["dt"], r["status"], r["iterations"], r["steps_done"])
                      for r in csv.DictReader(f))
ref = table(f"{out}/serial1/stability.csv")
for mode in ("serial", "cluster"):
    for i in range(1, repeats + 1):
        t = table(f"{out}/{mode}{i}/stability.csv")
        diff = sum(a != b for a, b in zip(t, ref)) + abs(len(t) - len(ref))
        print(f"{mode}{i}: {len(t)} cases, {diff} differ from serial1 in status, iterations or steps")
PY
