#!/usr/bin/env bash
# The GPU rows of reports/scaling.md in one call of a lent GPU machine with a time limit: the
# whole NGSIM I-80 sample and 1,000 generated followers at batches of 64, 1,000 again at each
# other candidate batch size, then 10,000 and 100,000 at the batch with the lowest measured cost
# per vehicle, each only if that cost says it ends before the deadline (a row that cannot finish
# is not started, and the log says so). A candidate row is cut at CANDIDATE_LIMIT seconds: under
# `vmap` a batch runs until its slowest vehicle ends, and a batch of 1,000 once did not finish.
# Processes after the first share a persistent compilation cache, so a later row of a shape
# already compiled reports the cache's load time as its compile time.
#
#   benchmarks/gpu_scaling.sh OUT_FOLDER SECONDS_AVAILABLE
#
# Environment (defaults): BATCHES ("64 256"), LARGE_SIZES ("10000 100000"), CANDIDATE_LIMIT (120),
# BENCH_ARGS (extra bench_scaling.py arguments, "" ; e.g. "--particles 32" for a dry run on CPU),
# WORKDIR (a new temporary folder; a folder holding the generated followers read once before),
# SKIP_NGSIM (empty; set: no NGSIM row).
# Each (source, batch) writes its own folder of bench_scaling.py rows under OUT_FOLDER; merge
# them into reports/scaling/runs.jsonl, with the commit the tree was at, and run
# `python benchmarks/bench_scaling.py --report-only`.
set -uo pipefail
out=${1:?output folder}
available=${2:?seconds available}
batches=${BATCHES:-64 256}
large_sizes=${LARGE_SIZES:-10000 100000}
candidate_limit=${CANDIDATE_LIMIT:-120}
deadline=$(($(date +%s) + available))
work=${WORKDIR:-$(mktemp -d)}
export JAX_COMPILATION_CACHE_DIR="$work/jax-cache"
mkdir -p "$out"

bench() {  # one bench_scaling.py run, stopped at LIMIT seconds or the deadline, whichever first
    local limit=$1
    shift
    local left=$((deadline - $(date +%s)))
    timeout "$((limit < left ? limit : left))" python3 benchmarks/bench_scaling.py --modes batched \
        --workdir "$work" ${BENCH_ARGS:-} "$@" || echo "stopped: exit $? (124: the time limit)"
}

per_vehicle() {  # the cost per vehicle of the last row in a folder's runs.jsonl, or nothing
    python3 -c 'import json,sys; print(json.loads(open(sys.argv[1]).read().splitlines()[-1])["per_vehicle_s"])' "$1/runs.jsonl" 2>/dev/null
}

fits() {  # whether SIZE vehicles at PER_VEHICLE seconds, plus start-up, end before the deadline
    python3 -c 'import sys; size, cost, left = float(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]); sys.exit(0 if size * cost * 1.2 + 60 < left else 1)' "$1" "$2" "$(($deadline - $(date +%s)))"
}

nvidia-smi -L || echo "no NVIDIA GPU"
[ -n "${SKIP_NGSIM:-}" ] || bench "$available" --source ngsim_i80_chains --sizes 0 --batch 64 --means --out "$out/ngsim"
best_batch="" cost=""
for batch in $batches; do
    bench "$candidate_limit" --sizes 1000 --batch "$batch" --out "$out/b$batch"
    measured=$(per_vehicle "$out/b$batch")
    echo "batch $batch: ${measured:-no row} s per vehicle"
    if [ -n "$measured" ] && { [ -z "$cost" ] || python3 -c "import sys; sys.exit(0 if $measured < $cost else 1)"; }; then
        best_batch=$batch cost=$measured
    fi
done
if [ -z "$best_batch" ]; then
    echo "no candidate batch finished 1,000 vehicles: the large rows are not started"
    exit 0
fi
echo "the large rows run at batch $best_batch ($cost s per vehicle)"
for size in $large_sizes; do
    if fits "$size" "$cost"; then
        bench "$available" --sizes "$size" --batch "$best_batch" --out "$out/b$best_batch"
        cost=$(per_vehicle "$out/b$best_batch")
    else
        echo "$size vehicles at $cost s each would not end before the deadline: not started"
    fi
done
