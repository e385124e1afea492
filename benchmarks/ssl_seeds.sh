#!/usr/bin/env bash
# The semi-supervised benchmark over several split seeds: one benchmarks.ssl_benchmark
# process per seed, then the summary over seeds and the issue-14 targets (BENCHMARKS.md).
# With a GPU the seeds run all at once (they share the GPU and its cores); without one they
# run one after another, each with every core (two torch processes on a few cores slow each
# other several-fold).
#
#   benchmarks/ssl_seeds.sh [ssl_benchmark.py options...]
#
# Settings (environment): DATA (data set root; generated when missing), WORLD (its world
# version when generated, default v1), RESOLUTION (its camera resolution, half or full,
# default half), CAMERA_DATA (a separate set, generator seed 7, generated when missing with
# CAMERA_WORLD (default WORLD), CAMERA_FRAMES (default 600) and RESOLUTION: the 2D detector's
# COCO stand-in is trained on it once, CAMERA_STEPS steps (default camera_init's), in
# CAMERA_RUN, before the seeds, with the options' --camera-set overrides; unset: no stand-in),
# RUNS (run directories), SEEDS, CONFIG, DEVICE, PARALLEL (1: seeds at once, 0: one after another;
# default 1 where nvidia-smi finds a GPU), THREADS (torch threads per process; default 1 at
# once, every core one after another), PYTHON, and STAGE_TIMEOUT (seconds each process may
# run; unset: no limit). A rerun skips finished runs and resumes unfinished ones.
set -euo pipefail

DATA=${DATA:-data/synth2k}
WORLD=${WORLD:-v1}
RESOLUTION=${RESOLUTION:-half}
CAMERA_WORLD=${CAMERA_WORLD:-$WORLD}
CAMERA_FRAMES=${CAMERA_FRAMES:-600}
RUNS=${RUNS:-runs/ssl}
CAMERA_RUN=${CAMERA_RUN:-$RUNS/camera}
SEEDS=${SEEDS:-0 1 2}
CONFIG=${CONFIG:-configs/ssl_cpu.toml}
DEVICE=${DEVICE:-auto}
if [ -z "${PARALLEL:-}" ]; then
    PARALLEL=0
    if nvidia-smi --list-gpus >/dev/null 2>&1; then PARALLEL=1; fi
fi
PYTHON=${PYTHON:-python3}
CORES=$("$PYTHON" -c 'import os; print(os.cpu_count())')
if [ "$PARALLEL" = 1 ]; then THREADS=${THREADS:-1}; else THREADS=${THREADS:-$CORES}; fi
mkdir -p "$RUNS/logs"

if [ ! -f "$DATA/ImageSets/val.txt" ]; then
    "$PYTHON" -m commands.main synth --out "$DATA" --frames 2000 --seed 0 --world "$WORLD" \
        --resolution "$RESOLUTION" --workers "$CORES" --quiet --overwrite
fi
camera=()
if [ -n "${CAMERA_DATA:-}" ]; then
    if [ ! -f "$CAMERA_DATA/ImageSets/val.txt" ]; then
        "$PYTHON" -m commands.main synth --out "$CAMERA_DATA" --frames "$CAMERA_FRAMES" \
            --seed 7 --world "$CAMERA_WORLD" --resolution "$RESOLUTION" --val-fraction 0.1 \
            --workers "$CORES" --quiet --overwrite
    fi
    # Once, before the seeds (at once they would share its run directory), with the stand-in's
    # overrides (--camera-set) that the seeds pass on, so each seed finds it finished.
    overrides=()
    args=("$@")
    for ((i = 0; i < ${#args[@]}; i++)); do
        if [ "${args[i]}" = --camera-set ] && [ $((i + 1)) -lt ${#args[@]} ]; then
            overrides+=(--set "${args[i + 1]}")
        fi
    done
    steps=()
    [ -n "${CAMERA_STEPS:-}" ] && steps=(--steps "$CAMERA_STEPS")
    OMP_NUM_THREADS=$CORES "$PYTHON" -m benchmarks.camera_init --config "$CONFIG" \
        --data "$CAMERA_DATA" --out "$CAMERA_RUN" --device "$DEVICE" ${steps[@]+"${steps[@]}"} \
        ${overrides[@]+"${overrides[@]}"} >"$RUNS/logs/camera.log" 2>&1
    camera=(--camera-data "$CAMERA_DATA" --camera-run "$CAMERA_RUN")
    [ -n "${CAMERA_STEPS:-}" ] && camera+=(--camera-steps "$CAMERA_STEPS")
fi
failed=0
run_seed() {
    OMP_NUM_THREADS=$THREADS ${STAGE_TIMEOUT:+timeout "$STAGE_TIMEOUT"} "$PYTHON" \
        -m benchmarks.ssl_benchmark --config "$CONFIG" --data "$DATA" --seed "$1" \
        --out "$RUNS/s$1" --device "$DEVICE" ${camera[@]+"${camera[@]}"} "${@:2}" \
        >"$RUNS/logs/s$1.log" 2>&1
}
for seed in $SEEDS; do
    if [ "$PARALLEL" = 1 ]; then
        run_seed "$seed" "$@" &
    else
        echo "seed $seed: $RUNS/logs/s$seed.log"
        run_seed "$seed" "$@" || failed=1
    fi
done
for job in $(jobs -p); do wait "$job" || failed=1; done
reports=()
for seed in $SEEDS; do
    [ -f "$RUNS/s$seed/ssl_benchmark.json" ] && reports+=("$RUNS/s$seed/ssl_benchmark.json")
done
if [ ${#reports[@]} -gt 0 ]; then
    "$PYTHON" -m benchmarks.ssl_summary "${reports[@]}" | tee "$RUNS/summary.md"
fi
exit $failed
