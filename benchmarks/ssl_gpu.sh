#!/usr/bin/env bash
# The semi-supervised benchmark over several split seeds, each (seed, method) run in its own
# process so that one GPU and its CPU cores are shared by all of them (BENCHMARKS.md).
#
#   benchmarks/ssl_gpu.sh prepare           # 2,000 synthetic frames + a labeled split per seed
#   benchmarks/ssl_gpu.sh pretrain          # labeled-only pre-training, one process per seed
#   benchmarks/ssl_gpu.sh ssl               # every method of METHODS for every seed, in parallel
#   benchmarks/ssl_gpu.sh report            # evaluation, pseudo-label quality, Figure 3 per seed
#                                           # (of the runs that finished)
#
# Settings (environment): DATA (data set root), RUNS (run directories), SEEDS, FRACTION,
# METHODS, SSL_STEPS, CONFIG, WORKERS (loader workers per process), DEVICE, LOGS, and
# STAGE_TIMEOUT (seconds each process of a stage may run; unset: no limit).
# Stages skip what is already finished, so an interrupted stage can be rerun.
set -euo pipefail

DATA=${DATA:-data/synth2k}
RUNS=${RUNS:-runs/ssl_gpu}
SEEDS=${SEEDS:-0 1 2}
FRACTION=${FRACTION:-0.05}
METHODS=${METHODS:-confidence,detmatch,detmatch-matching-only,detmatch-class-consistency}
SSL_STEPS=${SSL_STEPS:-600}
CONFIG=${CONFIG:-configs/ssl_cpu.toml}
WORKERS=${WORKERS:-1}
DEVICE=${DEVICE:-auto}
LOGS=${LOGS:-$RUNS/logs}
PYTHON=${PYTHON:-python3}
mkdir -p "$LOGS"

bench() {  # bench SEED [ssl_benchmark.py arguments...]
    local seed=$1
    shift
    ${STAGE_TIMEOUT:+timeout "$STAGE_TIMEOUT"} "$PYTHON" benchmarks/ssl_benchmark.py --config "$CONFIG" --data "$DATA" \
        --out "$RUNS/s$seed" --split "train_labeled_${FRACTION}_s$seed" \
        --unlabeled-split "train_unlabeled_${FRACTION}_s$seed" --ssl-steps "$SSL_STEPS" \
        --device "$DEVICE" "$@"
}

wait_all() {  # wait for every background job; fail if any failed
    local failed=0
    for job in $(jobs -p); do wait "$job" || failed=1; done
    return $failed
}

case ${1:-} in
prepare)
    if [ ! -f "$DATA/ImageSets/val.txt" ]; then
        "$PYTHON" -m detmatch.cli synth --out "$DATA" --frames 2000 --seed 0 \
            --workers "$("$PYTHON" -c 'import os; print(os.cpu_count())')" --quiet
    fi
    for seed in $SEEDS; do
        "$PYTHON" -m detmatch.cli split --data "$DATA" --fraction "$FRACTION" --seed "$seed"
    done
    ;;
pretrain)
    for seed in $SEEDS; do
        bench "$seed" --methods "" --train-only --workers "$WORKERS" \
            >"$LOGS/pretrain_s$seed.log" 2>&1 &
    done
    wait_all
    ;;
ssl)
    for seed in $SEEDS; do
        for method in ${METHODS//,/ }; do
            bench "$seed" --methods "$method" --train-only --workers "$WORKERS" \
                >"$LOGS/${method}_s$seed.log" 2>&1 &
        done
    done
    wait_all
    ;;
report)
    for seed in $SEEDS; do
        bench "$seed" --methods "$METHODS" --workers "$WORKERS" --report-only \
            >"$LOGS/report_s$seed.log" 2>&1 &
    done
    wait_all
    ;;
*)
    echo "usage: $0 prepare|pretrain|ssl|report  (settings: see the header)" >&2
    exit 2
    ;;
esac
