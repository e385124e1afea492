"""DetMatch's matching threshold tau_hung against confidence thresholding, by pseudo-label
quality on labeled frames (the paper's Tables 4/5 ask how tau_hung moves accuracy; this asks
the cheaper question first: how it moves the pseudo-labels the students learn from).

    python -m benchmarks.tau_hung_sweep --runs runs/ssl_s0_v2/pretrain runs/ssl_s1_v2/pretrain \
        runs/ssl_s2_v2/pretrain --data data/synth2k --split train_dev0.1

Each run's teachers label the split's frames once; the same detections are then filtered by
confidence thresholding and by the matching at each tau_hung (benchmarks/ssl_benchmark.py's
rules, 3D boxes out of the camera's view by the tau_3d fallback) and scored against the frames'
labels: precision / recall / F1 per modality and class, pooled over the runs. The default split
is dev: never val.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch
from tqdm import tqdm

from benchmarks.ssl_benchmark import IOU_2D, IOU_3D, pseudo_label_sets
from detmatch.data.dataset import FrameDataset, collate
from detmatch.eval.pseudo_labels import pseudo_label_quality
from detmatch.inference import predict_batch
from detmatch.models.build import load_detectors

MODALITIES = ("3d", "2d")


def teacher_detections(run: str, data: str, split: str) -> tuple[list, list, object]:
    """The run's detections on every frame of the split: [(sample, det_2d, det_3d)], the
    frames' labels, and the run's config."""
    loaded = load_detectors(run)
    config = loaded.config.replace("data", root=data)
    dataset = FrameDataset(
        data, split, config.data.classes, config.data.image_size, loaded.model_3d.grid
    )
    loader = torch.utils.data.DataLoader(dataset, batch_size=4, collate_fn=collate)
    rows, labels = [], []
    for batch in tqdm(loader, desc=f"teachers of {run}", file=sys.stderr):
        for sample, (det_2d, det_3d) in zip(
            batch.samples, predict_batch(loaded.model_2d, loaded.model_3d, batch), strict=True
        ):
            rows.append((sample, det_2d, det_3d))
            labels.append(dataset.kitti.load_frame(sample.frame_id).labels)
    return rows, labels, config


def counts(rows: list, labels: list, config, classes, rule: str) -> dict:
    """{(modality, class): [tp, pseudo-labels, objects]} of one rule over one run's frames."""
    pseudo = [pseudo_label_sets(d2, d3, s, classes, config)[rule] for s, d2, d3 in rows]
    quality = pseudo_label_quality(pseudo, labels, classes, IOU_3D, IOU_2D)
    return {
        (m, c): np.array([quality[c][m][k] for k in ("tp", "num_pseudo", "num_gt")])
        for m in MODALITIES
        for c in classes
    }


def f1_cell(total: np.ndarray) -> str:
    tp, pseudo, objects = total
    precision, recall = tp / max(pseudo, 1), tp / max(objects, 1)
    f1 = 2 * precision * recall / max(precision + recall, 1e-12)
    return f"{precision:.3f} / {recall:.3f} / **{f1:.3f}**"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", nargs="+", required=True, help="pre-trained run directories")
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", default="train_dev0.1")
    parser.add_argument("--taus", default="-1,-1.25,-1.5,-1.75,-2",
                        help="comma-separated tau_hung values")  # fmt: skip
    args = parser.parse_args()
    if args.split == "val":
        parser.error("choices are made on dev: --split val is not allowed")
    taus = [float(t) for t in args.taus.split(",")]
    totals: dict[str, dict] = {}
    classes = ()
    for run in args.runs:
        rows, labels, config = teacher_detections(run, args.data, args.split)
        classes = config.data.classes
        rules = {"confidence": ("confidence", config)}
        for tau in taus:
            rules[f"DetMatch, tau_hung {tau:g}"] = ("detmatch", config.replace("ssl", tau_hung=tau))
        for name, (rule, rule_config) in rules.items():
            found = counts(rows, labels, rule_config, classes, rule)
            for key, value in found.items():
                totals.setdefault(name, {}).setdefault(key, np.zeros(3))
                totals[name][key] += value
    print(f"\nPseudo-labels on {args.split} ({len(args.runs)} runs pooled): "
          "precision / recall / F1")  # fmt: skip
    header = [f"{m.upper()} {c}" for m in MODALITIES for c in classes]
    print("| rule | " + " | ".join(header) + " |")
    print("|---|" + "---|" * len(header))
    for name, found in totals.items():
        cells = [f1_cell(found[(m, c)]) for m in MODALITIES for c in classes]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("\nrerun: python -m benchmarks.tau_hung_sweep " + " ".join(sys.argv[1:]))


if __name__ == "__main__":
    main()
