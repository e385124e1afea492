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

from tqdm import tqdm

from benchmarks.ssl_benchmark import IOU_2D, IOU_3D, pseudo_label_sets, teacher_frames
from detmatch.data.dataset import FrameDataset
from detmatch.eval.pseudo_labels import MODALITIES, pooled_precision_recall_f1, pseudo_label_quality
from detmatch.models.build import load_detectors


def run_quality(run: str, data: str, split: str, taus: list[float]) -> tuple[dict, tuple]:
    """{rule name: {(modality, class): pseudo_label_quality row}} of one run's teachers on the
    split's frames (confidence thresholding and the matching at each tau_hung), and the
    classes."""
    loaded = load_detectors(run)
    config = loaded.config.replace("data", root=data)
    classes = config.data.classes
    dataset = FrameDataset(data, split, classes, config.data.image_size, loaded.model_3d.grid)
    frames = list(tqdm(teacher_frames(loaded, dataset, len(dataset)), total=len(dataset),
                       desc=f"teachers of {run}", file=sys.stderr))  # fmt: skip
    labels = [frame[3] for frame in frames]
    per_tau = {
        tau: [pseudo_label_sets(d2, d3, sample, classes, config.replace("ssl", tau_hung=tau))
              for sample, d2, d3, _ in frames]
        for tau in taus
    }  # fmt: skip
    rules = {"confidence": [sets["confidence"] for sets in per_tau[taus[0]]]}
    for tau, sets in per_tau.items():
        rules[f"DetMatch, tau_hung {tau:g}"] = [frame["detmatch"] for frame in sets]
    quality = {}
    for name, pseudo in rules.items():
        rows = pseudo_label_quality(pseudo, labels, classes, IOU_3D, IOU_2D)
        quality[name] = {(m, c): rows[c][m] for m in MODALITIES for c in classes}
    return quality, classes


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
    pooled: dict[str, dict] = {}
    classes: tuple = ()
    for run in args.runs:
        quality, classes = run_quality(run, args.data, args.split, taus)
        for name, rows in quality.items():
            for key, row in rows.items():
                pooled.setdefault(name, {}).setdefault(key, []).append(row)
    print(f"\nPseudo-labels on {args.split} ({len(args.runs)} runs pooled): "
          "precision / recall / F1")  # fmt: skip
    keys = [(m, c) for m in MODALITIES for c in classes]
    print("| rule | " + " | ".join(f"{m.upper()} {c}" for m, c in keys) + " |")
    print("|---|" + "---|" * len(keys))
    for name, rows in pooled.items():
        cells = []
        for key in keys:
            precision, recall, f1 = pooled_precision_recall_f1(rows[key])
            cells.append(f"{precision:.3f} / {recall:.3f} / **{f1:.3f}**")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("\nrerun: python -m benchmarks.tau_hung_sweep " + " ".join(sys.argv[1:]))


if __name__ == "__main__":
    main()
