"""How many in-view 3D teacher detections the camera did not confirm DetMatch should keep as
LiDAR-only pseudo-labels (`[ssl] tau_3d_unmatched`), chosen on the labeled dev split.

    python benchmarks/lidar_only_threshold.py runs/long_s2/pretrain --data data/synth2k

Runs a pre-trained checkpoint's detectors (the teachers a teacher-student stage starts from)
over the dev frames, whose labels are known, and prints per class the 3D pseudo-label
precision / recall / F1 of: confidence thresholding (tau_3D); DetMatch's matched labels
alone (the paper); and DetMatch plus the unmatched in-view detections above each candidate
score. 3D boxes outside the camera's view are left out of every row (they are LiDAR-only under
every rule), as in ssl_benchmark.py's pseudo-label table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from detmatch.config import apply_overrides, load_config
from detmatch.data.dataset import FrameDataset
from detmatch.eval.pseudo_labels import pooled_precision_recall_f1, pseudo_label_quality
from detmatch.geometry import boxes_touching_image
from detmatch.models.build import load_detectors
from detmatch.pseudo_labels import confident_detections, match_detections

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ssl_benchmark import IOU_2D, IOU_3D, as_labels, teacher_frames  # noqa: E402

SCORES = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="pre-training checkpoint or run directory")
    parser.add_argument("--config", default="configs/ssl_cpu.toml")
    parser.add_argument("--data", default="data/synth2k")
    parser.add_argument("--split", default="train_dev0.1", help="a labeled split (never val)")
    parser.add_argument("--scores", type=float, nargs="+", default=SCORES)
    args = parser.parse_args()
    if args.split.startswith("val"):
        parser.error("choose on a labeled dev split, never on val")

    config = apply_overrides(load_config(args.config), [f"data.root={args.data}"])
    ssl, data = config.ssl, config.data
    loaded = load_detectors(args.checkpoint)
    dataset = FrameDataset(
        data.root, args.split, data.classes, data.image_size, loaded.model_3d.grid
    )
    rules = {"confidence": [], "detmatch": [], **{f"detmatch+{s:g}": [] for s in args.scores}}
    truth = []
    for sample, det_2d, det_3d, labels in teacher_frames(loaded, dataset, len(dataset)):
        truth.append(labels)
        size = sample.image_transform.original_size
        view = det_3d[boxes_touching_image(det_3d.boxes, sample.calib, size)]
        confident = confident_detections(view, ssl.tau_3d)
        rules["confidence"].append(
            as_labels([data.classes[c] for c in confident.classes], confident.boxes,
                      np.zeros((len(confident), 4)), confident.scores)
        )  # fmt: skip
        for name, score in [("detmatch", None), *((f"detmatch+{s:g}", s) for s in args.scores)]:
            kept = match_detections(view, det_2d, sample.calib, size, ssl.tau_hung, None, score)
            rules[name].append(
                as_labels([data.classes[c] for c in kept.class_3d], kept.boxes_3d,
                          np.zeros((len(kept), 4)), kept.score_3d)
            )  # fmt: skip

    print(f"3D pseudo-labels of {args.checkpoint} on {args.split} ({len(truth)} frames)")
    print("| rule | " + " | ".join(f"{c} P / R / F1" for c in data.classes) + " | pooled F1 |")
    print("|---" * (len(data.classes) + 2) + "|")
    for name, rows in rules.items():
        quality = pseudo_label_quality(rows, truth, data.classes, IOU_3D, IOU_2D)
        cells = []
        for c in data.classes:
            q = quality[c]["3d"]
            p, r = q["precision"], q["recall"]
            cells.append(f"{p:.2f} / {r:.2f} / {2 * p * r / (p + r) if p + r else 0:.2f}")
        pooled = pooled_precision_recall_f1([quality[c]["3d"] for c in data.classes])[2]
        print(f"| {name} | " + " | ".join(cells) + f" | {pooled:.3f} |")
    print(
        f"\nrerun: python benchmarks/lidar_only_threshold.py {args.checkpoint} --data {args.data}"
        f" --split {args.split}"
    )


if __name__ == "__main__":
    main()
