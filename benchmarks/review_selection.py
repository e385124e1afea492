"""Which frames a reviewer should see first: the share of all label errors that each review
selection puts in front of them, against the synthetic world's hidden labels.

    python -m benchmarks.review_selection --checkpoint RUN_OR_CKPT --data SYNTH_DIR
        [--split train_unlabeled_...] [--frames 600] [--budgets 0.05 0.10] [--work DIR]

A pre-trained checkpoint is exported (onnxruntime, as the service labels) and labels the
frames of --split (the first --frames of it) into a label store, as `detmatch label --store`
does; rerunning reuses the export and the stored frames. Each frame's labels are then scored
against its hidden labels (3D IoU, classes Car, Pedestrian, Cyclist in the 3D detector's
range; a label overlapping a Van or DontCare box by IoU >= 0.5 is not counted false):
- missed object: a ground-truth box no label overlaps by 3D IoU >= 0.5;
- false box: a label that overlaps no box by 3D IoU >= 0.5;
- wrong class: the best-overlapping label (IoU >= 0.5) has another class;
- loose box: the best-overlapping label has the class, but 3D IoU < 0.7.
For budgets of 5 % and 10 % of the frames: the share of all errors (and of each kind) in the
frames that `--select disagreement` (cross-modal), `--select least-confident` (lowest mean 3D
score) and `--select random` (mean of --random-draws seeds) pick. Target: disagreement >= 2x
random and above least-confident at both budgets. Two reference rows: summed doubt (the sum
of 1 - 3D score over a frame's labels, a stronger single-modality ranking than the mean) and
the oracle (the frames holding the most errors: the most any selection of that size can
reach).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import benchmark_parser, rerun
from detmatch.data.kitti import KittiDataset
from detmatch.data.selection import FrameSelection
from detmatch.geometry import pairwise_iou_3d
from serving.review import select_frames
from serving.store import LabelStore, list_frames

CLASSES = ("Car", "Pedestrian", "Cyclist")
IGNORED = ("Van", "DontCare", "Misc", "Truck", "Tram", "Person_sitting")
KINDS = ("missed", "false", "wrong class", "loose")
SELECTIONS = ("disagreement", "least-confident", "random")
ORACLE = "oracle (most true errors)"
SUMMED = "summed doubt (sum of 1 - 3D score)"


def frame_errors(labels: dict, truth_names: np.ndarray, truth_boxes: np.ndarray,
                 point_range: list[float]) -> dict[str, int]:  # fmt: skip
    """The errors of one frame's labels against its hidden labels (see the docstring)."""
    x0, y0, _, x1, y1, _ = point_range
    inside = (truth_boxes[:, 0] >= x0) & (truth_boxes[:, 0] < x1)
    inside &= (truth_boxes[:, 1] >= y0) & (truth_boxes[:, 1] < y1)
    wanted = inside & np.isin(truth_names, CLASSES)
    ignored = inside & np.isin(truth_names, IGNORED)
    records = labels["labels"]
    boxes = np.array([r["box_3d"] for r in records], dtype=np.float64).reshape(-1, 7)
    classes = np.array([r["class_3d"] for r in records])
    errors = dict.fromkeys(KINDS, 0)
    gt_boxes, gt_names = truth_boxes[wanted], truth_names[wanted]
    iou = pairwise_iou_3d(gt_boxes, boxes) if len(gt_boxes) and len(boxes) else np.zeros(
        (len(gt_boxes), len(boxes)))  # fmt: skip
    for g in range(len(gt_boxes)):
        best = int(np.argmax(iou[g])) if len(boxes) else -1
        if best < 0 or iou[g, best] < 0.5:
            errors["missed"] += 1
        elif classes[best] != gt_names[g]:
            errors["wrong class"] += 1
        elif iou[g, best] < 0.7:
            errors["loose"] += 1
    others = truth_boxes[ignored]
    for i in range(len(boxes)):
        overlaps = iou[:, i].max(initial=0.0)
        if len(others):
            overlaps = max(overlaps, pairwise_iou_3d(others, boxes[i : i + 1]).max())
        if overlaps < 0.5:
            errors["false"] += 1
    return errors


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--checkpoint", required=True, help="a run directory or a checkpoint")
    parser.add_argument("--data", required=True, help="a synthetic set (its hidden labels)")
    parser.add_argument("--split", default="train_unlabeled_0.025_s0_dev0.1")
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--budgets", nargs="+", type=float, default=[0.05, 0.10])
    parser.add_argument("--random-draws", type=int, default=50)
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="review_selection_"))
    work.mkdir(parents=True, exist_ok=True)
    repository, store = work / "models", work / "store"
    if not (repository / "000001").is_dir():
        from export.onnx_export import export_checkpoint

        export_checkpoint(args.checkpoint, repository, promote_version=True,
                          synthetic_frames=1, parity_frames_per_source=1)  # fmt: skip
    from serving.labeler import Labeler
    from serving.offline import label_split

    labeler = Labeler.from_repository(repository)
    dataset = KittiDataset(args.data)
    ids = (Path(args.data) / "ImageSets" / f"{args.split}.txt").read_text().split()
    ids = ids[: args.frames]
    (work / "ids.txt").write_text("".join(f"{i}\n" for i in ids))
    with LabelStore(store, "bench") as writer:
        label_split(labeler, args.data, FrameSelection(ids_file=work / "ids.txt"), None,
                    store=writer)  # fmt: skip
    point_range = json.loads((repository / "000001" / "manifest.json").read_text())
    point_range = _point_range(point_range)
    everything = select_frames(store)
    errors = {}
    for selected in everything:
        frame = dataset.load_frame(selected.record.frame_id, with_labels=True)
        errors[selected.record.key] = frame_errors(
            selected.labels, np.asarray(frame.labels.names), frame.labels.boxes_3d.data,
            point_range,
        )  # fmt: skip
    total = {kind: sum(e[kind] for e in errors.values()) for kind in KINDS}
    total_all = sum(total.values())
    frames = len(list_frames(store))
    rows = []
    for budget in args.budgets:
        count = max(1, round(budget * frames))
        shares = {}
        for selection in SELECTIONS:
            draws = range(args.random_draws) if selection == "random" else [0]
            per_kind = {kind: [] for kind in (*KINDS, "all")}
            for seed in draws:
                picked = select_frames(store, selection, count, seed=seed)
                held = {kind: sum(errors[s.record.key][kind] for s in picked) for kind in KINDS}
                for kind in KINDS:
                    per_kind[kind].append(held[kind] / max(total[kind], 1))
                per_kind["all"].append(sum(held.values()) / max(total_all, 1))
            shares[selection] = {kind: float(np.mean(v)) for kind, v in per_kind.items()}
        # A stronger single-modality ranking than the mean: the sum of (1 - 3D score) over a
        # frame's labels (more doubtful labels, more errors); not a product selection.
        doubt = {s.record.key: sum(1 - r["score_3d"] for r in s.labels["labels"])
                 for s in everything}  # fmt: skip
        summed = sorted(doubt, key=lambda key: (-doubt[key], key))[:count]
        shares[SUMMED] = {kind: sum(errors[k][kind] for k in summed) / max(total[kind], 1)
                          for kind in KINDS}  # fmt: skip
        shares[SUMMED]["all"] = sum(sum(errors[k].values()) for k in summed) / max(total_all, 1)
        best = sorted(errors, key=lambda key: -sum(errors[key].values()))[:count]
        shares[ORACLE] = {kind: sum(errors[k][kind] for k in best) / max(total[kind], 1)
                          for kind in KINDS}  # fmt: skip
        shares[ORACLE]["all"] = sum(sum(errors[k].values()) for k in best) / max(total_all, 1)
        rows.append({"budget": budget, "frames": count, "shares": shares})
    print(f"{frames} frames of {args.data} ({args.split}), labeled by {args.checkpoint}; "
          f"errors: {total_all} ({', '.join(f'{k} {v}' for k, v in total.items())})")  # fmt: skip
    print("\n| budget | frames | selection | all errors | missed | false | wrong class | loose "
          "| x random |")  # fmt: skip
    print("| ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for row in rows:
        random_share = row["shares"]["random"]["all"]
        for selection in (*SELECTIONS, SUMMED, ORACLE):
            share = row["shares"][selection]
            print(f"| {row['budget']:.0%} | {row['frames']} | {selection} | {share['all']:.1%} | "
                  + " | ".join(f"{share[k]:.1%}" for k in KINDS)
                  + f" | {share['all'] / max(random_share, 1e-9):.2f} |")  # fmt: skip
    for row in rows:
        shares = row["shares"]
        met = (shares["disagreement"]["all"] >= 2 * shares["random"]["all"]
               and shares["disagreement"]["all"] > shares["least-confident"]["all"])  # fmt: skip
        print(f"budget {row['budget']:.0%}: target (>= 2x random and above least-confident) "
              f"{'met' if met else 'missed'}")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "errors": total}, indent=2) + "\n")
    argv = ["--checkpoint", args.checkpoint, "--data", args.data, "--split", args.split,
            "--frames", str(args.frames), "--budgets", *map(str, args.budgets)]  # fmt: skip
    print(f"\nrerun: {rerun('review_selection', argv)}")


def _point_range(manifest: dict) -> list[float]:
    """The 3D detector's point cloud range from a manifest."""
    found = []

    def walk(node) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                if key == "point_cloud_range":
                    found.append(value)
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(manifest)
    if not found:
        raise SystemExit("the manifest names no point_cloud_range")
    return [float(v) for v in found[0]]


if __name__ == "__main__":
    main()
