"""KITTI evaluation speed: a KITTI-val-sized set (3,769 frames), three classes, all metrics.

Generates random KITTI-like ground truth (several objects per frame of six classes, varied
difficulty, DontCare regions) and noisy scored predictions (misses, duplicates, confused
classes, false positives), writes them as real label / result files in a temporary directory
and times `evaluate_dirs` end to end, then its parts: reading the files, flattening, the
2D / BEV / 3D overlaps and the matching statistics. Numba's compile time (cold cache) and its
cache-load time are measured in fresh subprocesses.

    python -m benchmarks.eval_speed [--frames 3769] [--seed 0] [--repeats 3] [--clutter 8]
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import benchmark_parser, rerun
from detmatch.data.kitti import KittiObjects, read_objects, write_objects
from detmatch.eval.kitti import (
    NEIGHBOUR_CLASS,
    evaluate_dirs,
    format_table,
    match_statistics,
    prepare,
)
from detmatch.eval.kitti_overlaps import flatten_objects, frame_overlaps

CLASSES = ("Car", "Pedestrian", "Cyclist")
NAMES = np.array(["Car", "Pedestrian", "Cyclist", "Van", "Person_sitting", "Truck", "DontCare"])
SHARES = np.array([0.55, 0.14, 0.07, 0.07, 0.02, 0.04, 0.11])
HWL = {"Car": (1.5, 1.6, 3.9), "Pedestrian": (1.75, 0.6, 0.8), "Cyclist": (1.7, 0.6, 1.8),
       "Van": (2.2, 1.9, 5.0), "Person_sitting": (1.3, 0.6, 0.9),
       "Truck": (3.2, 2.5, 10.0)}  # fmt: skip
COMPILE_SNIPPET = """
import time
import numpy as np
from detmatch.data.kitti import KittiObjects
start = time.perf_counter()
from detmatch.eval.kitti import evaluate
one = KittiObjects(names=np.array(["Car"], dtype=object), truncated=np.zeros(1),
    occluded=np.zeros(1, dtype=np.int64), alpha=np.zeros(1), bbox=np.array([[0, 0, 50, 50.]]),
    dimensions=np.array([[1.5, 1.6, 3.9]]), location=np.array([[0, 1.6, 10.]]),
    rotation_y=np.zeros(1), score=np.ones(1))
evaluate([one], [one], ["Car", "Pedestrian", "Cyclist"])
print(time.perf_counter() - start)
"""


def random_frame(
    rng: np.random.Generator, clutter_rate: float
) -> tuple[KittiObjects, KittiObjects]:
    """One frame of ground truth and predictions (clutter_rate: mean false positives)."""
    n = int(np.clip(rng.poisson(7), 1, 25))
    names = rng.choice(NAMES, n, p=SHARES)
    real = names != "DontCare"
    hwl = np.array([HWL.get(name, (1.5, 1.6, 3.9)) for name in names]) * rng.uniform(
        0.85, 1.15, (n, 3)
    )
    location = np.stack(
        [rng.uniform(-20, 20, n), rng.normal(1.65, 0.1, n), rng.uniform(4, 70, n)], 1
    )
    rotation_y = rng.uniform(-np.pi, np.pi, n)
    height = np.clip(720.0 * hwl[:, 0] / location[:, 2], 8, 300)
    width = (
        height
        * np.where(np.isin(names, ["Car", "Van", "Truck"]), 1.6, 0.5)
        * rng.uniform(0.6, 1.4, n)
    )
    x1 = np.clip(620 + 720 * location[:, 0] / location[:, 2] - width / 2, 0, 1200)
    y1 = np.clip(180 - height / 3, 0, 300)
    bbox = np.stack([x1, y1, np.minimum(x1 + width, 1241), y1 + height], 1)
    gt = KittiObjects(
        names=names.astype(object),
        truncated=np.where(real, rng.choice([0.0, 0.0, 0.0, 0.2, 0.4, 0.7], n), -1.0),
        occluded=np.where(real, rng.choice([0, 0, 1, 1, 2, 3], n), -1),
        alpha=np.where(real, rotation_y - np.arctan2(location[:, 0], location[:, 2]), -10.0),
        bbox=bbox,
        dimensions=np.where(real[:, None], hwl, -1.0),
        location=np.where(real[:, None], location, -1000.0),
        rotation_y=np.where(real, rotation_y, -10.0),
    )

    # Detections: jittered ground truth (85 % found, 15 % twice, 5 % wrong class) + clutter.
    found = np.flatnonzero(real & (rng.random(n) < 0.85))
    found = np.concatenate([found, found[rng.random(found.size) < 0.15]])
    m = found.size
    clutter = int(rng.poisson(clutter_rate))
    det_names = np.concatenate([names[found], rng.choice(NAMES[:4], clutter)])
    confused = rng.random(m + clutter) < 0.05
    det_names[confused] = rng.choice(NAMES[:3], int(confused.sum()))
    clutter_rows = rng.integers(0, n, clutter)
    det_hwl = np.concatenate([hwl[found] * rng.normal(1, 0.05, (m, 3)), hwl[clutter_rows]])
    det_location = np.concatenate(
        [
            location[found] + rng.normal(0, 0.1, (m, 3)),
            location[clutter_rows] + rng.normal(0, 4, (clutter, 3)),
        ]
    )
    det_rotation = np.concatenate(
        [rotation_y[found] + rng.normal(0, 0.1, m), rng.uniform(-np.pi, np.pi, clutter)]
    )
    det_bbox = np.concatenate(
        [
            bbox[found] + rng.normal(0, 3, (m, 4)),
            bbox[clutter_rows] + rng.normal(0, 40, (clutter, 4)),
        ]
    )
    det_bbox[:, 2:] = np.maximum(det_bbox[:, 2:], det_bbox[:, :2] + 2)
    scores = np.concatenate([rng.beta(5, 2, m), rng.beta(1.5, 5, clutter)])
    dt = KittiObjects(
        names=det_names.astype(object),
        truncated=np.zeros(m + clutter),
        occluded=np.zeros(m + clutter, dtype=np.int64),
        alpha=det_rotation - np.arctan2(det_location[:, 0], det_location[:, 2]),
        bbox=det_bbox,
        dimensions=det_hwl,
        location=det_location,
        rotation_y=det_rotation,
        score=scores,
    )
    return gt, dt


def best_of(repeats: int, run) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def compile_times() -> tuple[float, float]:
    """(seconds for the first evaluation with an empty numba cache, with the cache warm)."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        cold = float(subprocess.run([sys.executable, "-c", COMPILE_SNIPPET], env=env,
                                    capture_output=True, text=True, check=True).stdout)  # fmt: skip
        warm = float(subprocess.run([sys.executable, "-c", COMPILE_SNIPPET], env=env,
                                    capture_output=True, text=True, check=True).stdout)  # fmt: skip
    return cold, warm


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--frames", type=int, default=3769)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--clutter", type=float, default=8.0, help="mean false positives per frame")
    args = parser.parse_args()

    cold, warm = compile_times()
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        gt_dir, pred_dir = Path(tmp) / "label_2", Path(tmp) / "results"
        ids = [f"{i:06d}" for i in range(args.frames)]
        for frame_id in ids:
            gt, dt = random_frame(rng, args.clutter)
            write_objects(gt_dir / f"{frame_id}.txt", gt)
            write_objects(pred_dir / f"{frame_id}.txt", dt)

        evaluate_dirs(gt_dir, pred_dir, ids[:10], CLASSES)  # loads the numba cache
        total, results = best_of(
            args.repeats, lambda: evaluate_dirs(gt_dir, pred_dir, ids, CLASSES)
        )
        read, (gt, dt) = best_of(
            args.repeats,
            lambda: (
                [read_objects(gt_dir / f"{i}.txt") for i in ids],
                [read_objects(pred_dir / f"{i}.txt") for i in ids],
            ),
        )
        relevant = {c.lower() for c in CLASSES} | set(NEIGHBOUR_CLASS.values())
        flatten, (gt_flat, _, dt_flat) = best_of(
            args.repeats, lambda: flatten_objects(gt, dt, relevant)
        )
        overlaps, _ = best_of(args.repeats, lambda: frame_overlaps(gt_flat, dt_flat))
        prepared = prepare(gt, dt, CLASSES)
        stats, _ = best_of(args.repeats, lambda: match_statistics(prepared))

    num_gt = sum(len(g) for g in gt)
    num_dt = sum(len(d) for d in dt)
    num_pairs = int(prepared.overlap_offsets[-1])
    print(format_table(results))
    print()
    print(
        f"{args.frames} frames, {num_gt} label rows, {num_dt} detections, {num_pairs} same-frame"
        f" pairs, classes {','.join(CLASSES)}, all metrics; median of {args.repeats} runs"
    )
    print(f"evaluate_dirs end to end   {total:7.2f} s")
    print(f"  reading the files        {read:7.2f} s")
    print(f"  flattening               {flatten:7.2f} s")
    print(f"  overlaps (2D, BEV, 3D)   {overlaps:7.2f} s")
    print(f"  matching statistics      {stats:7.2f} s")
    print(f"numba first call, cold cache (compile)  {cold:6.2f} s")
    print(f"numba first call, warm cache (load)     {warm:6.2f} s")
    print(f"rerun: {rerun('eval_speed')}")


if __name__ == "__main__":
    main()
