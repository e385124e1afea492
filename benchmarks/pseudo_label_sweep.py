"""Pseudo-label precision at equal recall: DetMatch's labels against confidence thresholding
swept over its threshold, per class and modality.

    python -m benchmarks.pseudo_label_sweep runs/long_s1/pretrain \
        --split train_unlabeled_0.05_s1_dev0.1          # from the repository's root

ssl_benchmark.py's pseudo-label table compares the two rules at their configured thresholds
(tau_3D, tau_2D). At tau_2D = 0.7 confidence thresholding passes a few near-certain 2D boxes,
so its precision there says little about the rule. This runs a pre-trained checkpoint's
detectors (the teachers a teacher-student stage starts from) over the first frames of a split
whose labels are known but unread in training (the unlabeled split, as in the benchmark's
table, or dev; never val), then prints per class and modality DetMatch's precision / recall
and confidence thresholding's best precision over the thresholds (0.02 to 0.98) whose recall
reaches DetMatch's: the two rules at equal recall, the baseline at its best there. 3D boxes
outside the camera's view take no part, as in the benchmark's table.
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.ssl_benchmark import (
    IOU_2D,
    IOU_3D,
    modality_labels,
    pseudo_label_sets,
    teacher_frames,
)
from detmatch.config import apply_overrides, load_config
from detmatch.data.dataset import FrameDataset
from detmatch.eval.pseudo_labels import MODALITIES, pseudo_label_quality
from detmatch.geometry import boxes_touching_image
from detmatch.models.build import load_detectors
from detmatch.pseudo_labels import confident_detections
from detmatch.structures import Labels

THRESHOLDS = tuple(round(0.02 * k, 2) for k in range(1, 50))
PRINTED = tuple(round(0.1 * k, 1) for k in range(1, 10))


def confidence_rows(det_2d, view_3d, threshold: float, classes) -> Labels:
    """Confidence thresholding's labels of one frame at one threshold, both modalities."""
    kept_3d = confident_detections(view_3d, threshold)
    kept_2d = confident_detections(det_2d, threshold)
    return modality_labels(
        (kept_3d.boxes, kept_3d.classes, kept_3d.scores),
        (kept_2d.boxes, kept_2d.classes, kept_2d.scores),
        classes,
    )


def at_equal_recall(sweep: dict[float, dict], recall: float) -> tuple[float, dict] | None:
    """Of the thresholds whose recall reaches `recall`, the one of highest precision (the
    strictest of equals), with its row: the rule at its best at that recall; None if none
    reaches it."""
    reached = [(row["precision"], t) for t, row in sweep.items() if row["recall"] >= recall]
    return (max(reached)[1], sweep[max(reached)[1]]) if reached else None


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("checkpoint", type=Path, help="pre-training checkpoint or run directory")
    parser.add_argument("--split", required=True, help="a split with known labels (never val)")
    parser.add_argument("--config", default="configs/ssl_cpu.toml")
    parser.add_argument("--data", default="data/synth2k")
    parser.add_argument("--frames", type=int, default=200, help="first N frames of the split")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args()
    if args.split.startswith("val"):
        parser.error("val is scored once, for the report: use the unlabeled or a dev split")

    config = apply_overrides(load_config(args.config), [f"data.root={args.data}", *args.set])
    classes = config.data.classes
    loaded = load_detectors(args.checkpoint)
    dataset = FrameDataset(
        config.data.root, args.split, classes, config.data.image_size, loaded.model_3d.grid
    )
    truth, detmatch, swept = [], [], {t: [] for t in THRESHOLDS}
    for sample, det_2d, det_3d, labels in teacher_frames(loaded, dataset, args.frames):
        truth.append(labels)
        detmatch.append(pseudo_label_sets(det_2d, det_3d, sample, classes, config)["detmatch"])
        size = sample.image_transform.original_size
        view = det_3d[boxes_touching_image(det_3d.boxes, sample.calib, size)]
        for threshold in THRESHOLDS:
            swept[threshold].append(confidence_rows(det_2d, view, threshold, classes))

    def quality(rows):
        return pseudo_label_quality(rows, truth, classes, IOU_3D, IOU_2D)

    ours = quality(detmatch)
    sweep = {t: quality(rows) for t, rows in swept.items()}
    print(f"pseudo-labels of {args.checkpoint} on {args.split} ({len(truth)} frames)\n")
    print("| modality | class | DetMatch P / R | confidence at equal recall: threshold, P / R |"
          " precision gain |")  # fmt: skip
    print("|---|---|---|---|---|")
    for modality in MODALITIES:
        for name in classes:
            row = ours[name][modality]
            per_threshold = {t: q[name][modality] for t, q in sweep.items()}
            equal = at_equal_recall(per_threshold, row["recall"])
            ours_cell = f"{row['precision']:.3f} / {row['recall']:.3f}"
            if equal is None:
                cells = "never reaches it | "
            else:
                t, q = equal
                cells = (f"{t:.2f}: {q['precision']:.3f} / {q['recall']:.3f} | "
                         f"{row['precision'] - q['precision']:+.3f}")  # fmt: skip
            print(f"| {modality.upper()} | {name} | {ours_cell} | {cells} |")
    print("\nconfidence thresholding swept (precision / recall):\n")
    header = [f"{m.upper()} {c}" for m in MODALITIES for c in classes]
    print("| threshold | " + " | ".join(header) + " |")
    print("|---" * (len(header) + 1) + "|")
    for t, q in ((t, sweep[t]) for t in PRINTED):
        cells = [
            f"{q[c][m]['precision']:.2f} / {q[c][m]['recall']:.2f}"
            for m in MODALITIES
            for c in classes
        ]
        print(f"| {t:.2f} | " + " | ".join(cells) + " |")
    print(f"\nrerun: {rerun('pseudo_label_sweep')}")


if __name__ == "__main__":
    main()
