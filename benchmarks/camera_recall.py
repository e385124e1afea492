"""Where the camera detector loses small objects: per class, of the moderate ground-truth
objects of a split (KITTI's moderate: height >= 25 px, occlusion <= 1, truncation <= 0.3), the
share that some 2D detection (score > the detector's threshold, any class) covers at IoU >= 0.5,
the share whose covering detection has the right class, and which class it had.

    python -m benchmarks.camera_recall --runs runs/f02_s0/pretrain runs/ssl_s0_v2/pretrain
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
import torch

from detmatch.data.dataset import FrameDataset, collate
from detmatch.eval.kitti import within_difficulty
from detmatch.geometry import pairwise_iou_2d
from detmatch.inference import predict_batch
from detmatch.models.build import load_detectors

MODERATE = 1
COVERED_IOU = 0.5


def camera_recall(run: str, split: str) -> dict[str, dict]:
    """{class: {"objects", "median_height", "covered", "right_class", "covered_as"}}."""
    loaded = load_detectors(run)
    config = loaded.config
    classes = config.data.classes
    frames = FrameDataset(
        config.data.root, split, classes, config.data.image_size, loaded.model_3d.grid
    )
    heights = {c: [] for c in classes}
    covered_as = {c: Counter() for c in classes}
    loader = torch.utils.data.DataLoader(frames, batch_size=4, collate_fn=collate)
    for batch in loader:
        predictions = predict_batch(loaded.model_2d, loaded.model_3d, batch)
        for sample, (detections, _) in zip(batch.samples, predictions, strict=True):
            objects = frames.kitti.read_objects(sample.frame_id)
            height = objects.bbox[:, 3] - objects.bbox[:, 1]
            moderate = within_difficulty(
                objects.bbox, objects.occluded, objects.truncated, MODERATE
            )
            for i in np.flatnonzero(moderate):
                name = str(objects.names[i])
                if name not in classes:
                    continue
                heights[name].append(height[i])
                if len(detections) == 0:
                    continue
                iou = pairwise_iou_2d(objects.bbox[i][None], detections.boxes)[0]
                best = int(np.argmax(iou))
                if iou[best] >= COVERED_IOU:
                    covered_as[name][classes[int(detections.classes[best])]] += 1
    report = {}
    for name in classes:
        count = len(heights[name])
        covered = sum(covered_as[name].values())
        report[name] = {
            "objects": count,
            "median_height": float(np.median(heights[name])) if count else None,
            "covered": covered / max(count, 1),
            "right_class": covered_as[name][name] / max(count, 1),
            "covered_as": dict(covered_as[name]),
        }
    return report


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", nargs="+", required=True, help="run directories or checkpoints")
    parser.add_argument("--split", default="train_dev0.1", help="never val while tuning")
    args = parser.parse_args()
    print("| run | class | objects | median height px | covered | right class | covered as |")
    print("|---|---|---|---|---|---|---|")
    for run in args.runs:
        for name, row in camera_recall(run, args.split).items():
            print(
                f"| {run} | {name} | {row['objects']} | {row['median_height']:.0f} "
                f"| {row['covered']:.2f} | {row['right_class']:.2f} | {row['covered_as']} |"
            )
    runs = " ".join(args.runs)
    print(f"\n    python -m benchmarks.camera_recall --runs {runs} --split {args.split}")


if __name__ == "__main__":
    main()
