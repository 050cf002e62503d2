#!/usr/bin/env bash
# The GPU rows of reports/scaling.md in one call of a lent GPU machine with a time limit: the
# whole NGSIM I-80 sample, 1,000 generated followers, then 10,000 and 100,000, each only if the
# measured cost per vehicle says it ends before the deadline (a row that cannot finish is not
# started, and the log says so). Batches of 64: a batch of 1,000 runs until its slowest vehicle
# ends and did not finish (reports/scaling.md).
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

bench() {  # one bench_scaling.py run, stopped at the deadline
    timeout "$((deadline - $(date +%s)))" python3 benchmarks/bench_scaling.py --modes batched \
        --workdir "$work" "$@" || echo "stopped: exit $? (124: the deadline)"
}

per_vehicle() {  # the cost per vehicle of the last row in a folder's runs.jsonl
    python3 -c 'import json,sys; print(json.loads(open(sys.argv[1]).read().splitlines()[-1])["per_vehicle_s"])' "$1/runs.jsonl"
}

fits() {  # whether SIZE vehicles at PER_VEHICLE seconds, plus start-up, end before the deadline
    python3 -c 'import sys; size, cost, left = float(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]); sys.exit(0 if size * cost * 1.2 + 60 < left else 1)' "$1" "$2" "$(($deadline - $(date +%s)))"
}

nvidia-smi -L
bench --source ngsim_i80_chains --sizes 0 --batch 64 --means --out "$out/ngsim"
bench --sizes 1000 --batch 64 --out "$out/b64"
cost=$(per_vehicle "$out/b64")
echo "$cost s per vehicle"
for size in 10000 100000; do
    if fits "$size" "$cost"; then
        bench --sizes "$size" --batch 64 --out "$out/b64"
        cost=$(per_vehicle "$out/b64")
    else
        echo "$size vehicles at $cost s each would not end before the deadline: not started"
    fi
done
