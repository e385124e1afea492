#!/usr/bin/env bash
# The semi-supervised benchmark over several split seeds: one benchmarks/ssl_benchmark.py
# process per seed, all at once (on a GPU machine they share the GPU and its cores; on the
# 2-core CPU run one seed at a time: SEEDS=0), then the summary over seeds (BENCHMARKS.md).
#
#   benchmarks/ssl_seeds.sh [ssl_benchmark.py options...]
#
# Settings (environment): DATA (data set root; generated when missing), RUNS (run
# directories), SEEDS, CONFIG, DEVICE, THREADS (torch threads per process), PYTHON, and
# STAGE_TIMEOUT (seconds each process may run; unset: no limit). A rerun skips finished runs.
set -euo pipefail

DATA=${DATA:-data/synth2k}
RUNS=${RUNS:-runs/ssl}
SEEDS=${SEEDS:-0 1 2}
CONFIG=${CONFIG:-configs/ssl_cpu.toml}
DEVICE=${DEVICE:-auto}
THREADS=${THREADS:-1}
PYTHON=${PYTHON:-python3}
mkdir -p "$RUNS/logs"

if [ ! -f "$DATA/ImageSets/val.txt" ]; then
    "$PYTHON" -m detmatch.cli synth --out "$DATA" --frames 2000 --seed 0 \
        --workers "$("$PYTHON" -c 'import os; print(os.cpu_count())')" --quiet
fi
failed=0
for seed in $SEEDS; do
    OMP_NUM_THREADS=$THREADS ${STAGE_TIMEOUT:+timeout "$STAGE_TIMEOUT"} "$PYTHON" \
        benchmarks/ssl_benchmark.py --config "$CONFIG" --data "$DATA" --seed "$seed" \
        --out "$RUNS/s$seed" --device "$DEVICE" "$@" >"$RUNS/logs/s$seed.log" 2>&1 &
done
for job in $(jobs -p); do wait "$job" || failed=1; done
reports=()
for seed in $SEEDS; do
    [ -f "$RUNS/s$seed/ssl_benchmark.json" ] && reports+=("$RUNS/s$seed/ssl_benchmark.json")
done
if [ ${#reports[@]} -gt 0 ]; then
    "$PYTHON" benchmarks/ssl_summary.py "${reports[@]}" | tee "$RUNS/summary.md"
fi
exit $failed
