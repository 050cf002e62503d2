#!/usr/bin/env bash
# The GPU rows of reports/scaling.md in one call of a lent GPU machine with a time limit: the
# whole NGSIM I-80 sample, 1,000 generated followers at two batch sizes, then 10,000 and 100,000
# at the faster batch size, each only if the measured cost per vehicle says it ends before the
# deadline (a row that cannot finish is not started, and the log says so).
#
#   benchmarks/gpu_scaling.sh OUT_FOLDER SECONDS_AVAILABLE
#
# Each (source, batch) writes its own folder of bench_scaling.py rows under OUT_FOLDER; merge
# them into reports/scaling/runs.jsonl, with the commit the tree was at, and run
# `python benchmarks/bench_scaling.py --report-only`.
set -uo pipefail
out=${1:?output folder}
available=${2:?seconds available}
deadline=$(($(date +%s) + available))
work=$(mktemp -d)
mkdir -p "$out"

bench() { python3 benchmarks/bench_scaling.py --modes batched --workdir "$work" "$@"; }

per_vehicle() {  # the cost per vehicle of the last row in a folder's runs.jsonl
    python3 -c 'import json,sys; print(json.loads(open(sys.argv[1]).read().splitlines()[-1])["per_vehicle_s"])' "$1/runs.jsonl"
}

fits() {  # whether SIZE vehicles at PER_VEHICLE seconds, plus start-up, end before the deadline
    python3 -c 'import sys; size, cost, left = float(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]); sys.exit(0 if size * cost * 1.2 + 60 < left else 1)' "$1" "$2" "$(($deadline - $(date +%s)))"
}

nvidia-smi -L
bench --source ngsim_i80_chains --sizes 0 --batch 64 --means --out "$out/ngsim"
bench --sizes 1000 --batch 64 --out "$out/b64"
bench --sizes 1000 --batch 1000 --out "$out/b1000"

best=64
cost=$(per_vehicle "$out/b64")
if [ -f "$out/b1000/runs.jsonl" ]; then
    big=$(per_vehicle "$out/b1000")
    if python3 -c "import sys; sys.exit(0 if $big < $cost else 1)"; then best=1000; cost=$big; fi
fi
echo "batch $best: $cost s per vehicle"
for size in 10000 100000; do
    if fits "$size" "$cost"; then
        bench --sizes "$size" --batch "$best" --out "$out/b$best"
        cost=$(per_vehicle "$out/b$best")
    else
        echo "$size vehicles at $cost s each would not end before the deadline: not started"
    fi
done
