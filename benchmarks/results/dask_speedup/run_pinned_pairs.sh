#!/bin/bash
# REPEATS interleaved pairs of the quick stability sweep: one process pinned to one core
# (taskset -c $SERIAL_CPUS, default 0; SERIAL_CPUS= leaves it unpinned; --jobs 1), then the
# embedded two-worker cluster (--jobs 2, one pinned worker per core). PROBLEMS=... runs a
# subset of the problems. Wall and CPU time of each command; then the ratio of each pair,
# their median, and the tables compared case by case with the first serial run.
# Run from the repository root on a quiet machine:
#   OUT=/tmp/dask_pairs bash benchmarks/results/dask_speedup/run_pinned_pairs.sh 3
set -e
repeats=${1:-3}
out=${OUT:-/tmp/dask_pairs}
serial_cpus=${SERIAL_CPUS-0}
problems=${PROBLEMS:+--problems $PROBLEMS}
mkdir -p "$out"
for i in $(seq "$repeats"); do
  for mode in serial cluster; do
    cmd=(.venv/bin/python); jobs=2
    if [ "$mode" = serial ]; then
      jobs=1; [ -n "$serial_cpus" ] && cmd=(taskset -c "$serial_cpus" .venv/bin/python)
    fi
    /usr/bin/time -o "$out/$mode$i.time" -f "%e %U %S" "${cmd[@]}" -m diffrax_vi.bench \
      stability --quick $problems --jobs "$jobs" --no-progress --out "$out/$mode$i" \
      > "$out/$mode$i.log" 2>&1
    read wall user sys < "$out/$mode$i.time"
    echo "$mode run $i: $wall s wall, $(echo "$user + $sys" | bc) s CPU (load average: $(cut -d' ' -f1-3 /proc/loadavg))"
  done
done
.venv/bin/python - "$out" "$repeats" <<'PY'
import csv, statistics, sys
out, repeats = sys.argv[1], int(sys.argv[2])
def wall(name):
    return float(open(f"{out}/{name}.time").read().split()[0])
def table(path):
    with open(path) as f:
        return sorted((r["problem"], r["dtype"], r["activation"], r["solver"], r["acceptance"],
                       r["dt"], r["status"], r["iterations"], r["steps_done"])
                      for r in csv.DictReader(f))
ratios = [wall(f"serial{i}") / wall(f"cluster{i}") for i in range(1, repeats + 1)]
for i, r in enumerate(ratios, 1):
    print(f"pair {i}: {wall(f'serial{i}'):.1f} s / {wall(f'cluster{i}'):.1f} s = {r:.2f}x")
print(f"median over {repeats} pairs: {statistics.median(ratios):.2f}x; "
      f"median walls {statistics.median(wall(f'serial{i}') for i in range(1, repeats + 1)):.1f} s / "
      f"{statistics.median(wall(f'cluster{i}') for i in range(1, repeats + 1)):.1f} s")
ref = table(f"{out}/serial1/stability.csv")
for mode in ("serial", "cluster"):
    for i in range(1, repeats + 1):
        t = table(f"{out}/{mode}{i}/stability.csv")
        diff = sum(a != b for a, b in zip(t, ref)) + abs(len(t) - len(ref))
        print(f"{mode}{i}: {len(t)} cases, {diff} differ from serial1 in status, iterations or steps")
PY
