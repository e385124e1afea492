"""The semi-supervised benchmark (docs/design.md section 5) for one split seed, from one command:
labeled-only vs its EMA control vs confidence thresholding vs DetMatch, from the same
pre-trained weights on the same labeled split, under the dev protocol.

    detmatch synth --out data/synth2k --frames 2000 --seed 0 --workers 2
    python -m benchmarks.ssl_benchmark --config configs/ssl_cpu.toml --data data/synth2k \
        --seed 0 --out runs/ssl_s0

Protocol: `detmatch split --fraction F --seed S --dev-fraction D` (made here when missing)
holds out a labeled dev split of train, the same for every seed, disjoint from the labeled
subset, the unlabeled pool and val. Every choice (schedules, learning rates, thresholds,
weights) is made on dev; val is scored once, at the end, for the report.

Stages (each skipped when its run directory already holds a finished checkpoint):
1. labeled-only pre-training on the labeled split ([train] steps and schedules), evaluated on
   dev every [train] eval_every steps: the learning curve;
2. each method of --methods from the pre-trained weights on the config's teacher-student stage
   ([ssl] steps at [ssl] lr_2d / lr_3d, constant after [ssl] warmup_steps; --ssl-steps and
   the pre-training rates x --ssl-lr-factor override it):
   labeled-only-control (the same schedule and EMA teacher, labeled frames only),
   confidence thresholding, DetMatch and its ablations, and every-label (the control on every
   label of the labeled and unlabeled frames: what the stage gives if every pseudo-label is
   right, a reference for a method's gain, not a method);
3. moderate R40 AP per class on dev (every run) and on val (once), 2D (bbox) and 3D, with the
   gain over the better of labeled-only and its control (the paper's Tables 1 and 2);
4. pseudo-label precision / recall / F1 on unlabeled frames against their hidden labels: the
   pre-trained teacher's detections filtered by each rule, 3D in the camera's view;
5. a PNG like the paper's Figure 3 (each 3D teacher box's true IoU against its max class score
   and its best 2D-3D matching cost, with Spearman correlations).
Writes OUT/ssl_benchmark.json, OUT/report.md and OUT/figure3.png and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from benchmarks import camera_init
from benchmarks.harness import benchmark_parser, rerun
from detmatch.checkpoints import list_checkpoints, run_evaluations
from detmatch.config import (
    DEVICES,
    PRESETS,
    ExperimentConfig,
    apply_overrides,
    load_config,
    teacher_student_config,
)
from detmatch.data.dataset import FrameDataset, Sample, collate
from detmatch.data.kitti import read_image_set, write_image_set
from detmatch.data.splits import dev_name, make_split, split_names
from detmatch.data.synth.world import read_resolution, read_world
from detmatch.eval.occlusion import LEVELS as OCCLUSION_LEVELS
from detmatch.eval.occlusion import LevelCurve, object_levels
from detmatch.eval.pseudo_labels import pooled_precision_recall_f1, pseudo_label_quality
from detmatch.geometry import (
    boxes_touching_image,
    pairwise_iou_2d,
    pairwise_iou_3d,
    pairwise_iou_bev,
    project_boxes_to_image,
)
from detmatch.inference import predict_batch
from detmatch.matching import matching_cost
from detmatch.matching_policy import MatchingPolicy
from detmatch.models.build import LoadedDetectors, build_detectors, load_detectors
from detmatch.pseudo_labels import confident_detections, match_detections
from detmatch.structures import Boxes2D, Boxes3D, Detections, Labels
from detmatch.training.distributed import DistributedContext, init_distributed
from detmatch.training.evaluation import evaluate_detectors
from detmatch.training.semi_supervised import trainer_type
from detmatch.training.trainer import SupervisedTrainer

# What each method name of --methods trains: config overrides (`section.key=value`) on the
# benchmark's config. "detmatch" is the defaults (what won on dev: LiDAR-only labels above 0.6
# with the 2D side protected); "detmatch-paper" the paper's constants (a named preset);
# "detmatch-matched-only" the paper's rule on the defaults (the default before 2026-12-05); the
# paper's Table 6 ablations set both consistency switches and keep the other defaults. The
# variants dev turned down (ignore regions, unprotected LiDAR-only labels, the authors'
# per-frame means with candidate NMS) went with their options; commit 651fd4f has them.
DETMATCH = "ssl.method=detmatch"
METHODS: dict[str, tuple[str, ...]] = {
    "control": ("ssl.method=labeled-only-control",),
    "confidence": ("ssl.method=confidence",),
    "detmatch": (DETMATCH,),
    "detmatch-paper": PRESETS["paper"],
    "detmatch-matched-only": (DETMATCH, "ssl.tau_3d_unmatched=1.0"),
    "detmatch-matching-only": (
        DETMATCH, "ssl.consistency_class=false", "ssl.consistency_box=false",
    ),
    "detmatch-class-consistency": (
        DETMATCH, "ssl.consistency_class=true", "ssl.consistency_box=false",
    ),
    "detmatch-box-consistency": (
        DETMATCH, "ssl.consistency_class=false", "ssl.consistency_box=true",
    ),
    "detmatch-full-consistency": (
        DETMATCH, "ssl.consistency_class=true", "ssl.consistency_box=true",
    ),
    # The box term trains a light second stage of the 3D detector instead of its dense head
    # (fresh at this stage: the pre-training has none).
    "detmatch-refine": (
        DETMATCH, "ssl.consistency_class=true", "ssl.consistency_box=true",
        "detector3d.refine=true",
    ),
    # Not a method: the control trained on every label of the labeled and unlabeled frames (dev
    # held out), the stage's schedule from the same weights: what it gives with right labels.
    "every-label": ("ssl.method=labeled-only-control",),
}  # fmt: skip
BASELINES = ("labeled-only", "control")

IOU_3D = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
IOU_2D = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}


def finished(run_dir: Path, steps: int) -> bool:
    found = list_checkpoints(run_dir)
    return bool(found) and found[-1].name == f"step_{steps:08d}.pt"


def train_stage(
    trainer_type, config: ExperimentConfig, run_dir: Path, context: DistributedContext
) -> float:
    """Train (resuming if interrupted) unless finished; returns the wall seconds spent."""
    if finished(run_dir, config.train.steps):
        return 0.0
    trainer = trainer_type(config, run_dir, context)
    trainer.resume()
    start = time.perf_counter()
    trainer.run()
    return time.perf_counter() - start


def every_label_split(args: argparse.Namespace) -> str:
    """ImageSets name of the labeled and unlabeled frames together (train without dev), written
    when missing: the every-label run's training frames."""
    labeled, unlabeled = split_names(args.fraction, args.seed, dev_fraction=args.dev_fraction)
    name = f"train_nodev{args.dev_fraction:g}"
    sets = Path(args.data) / "ImageSets"
    if not (sets / f"{name}.txt").exists():
        ids = read_image_set(sets / f"{labeled}.txt") + read_image_set(sets / f"{unlabeled}.txt")
        write_image_set(sets / f"{name}.txt", sorted(ids))
    return name


def splits(args: argparse.Namespace) -> tuple[str, str, str]:
    """(labeled, unlabeled, dev) ImageSets names of the seed, written when missing."""
    labeled, unlabeled = split_names(args.fraction, args.seed, dev_fraction=args.dev_fraction)
    dev = dev_name(args.dev_fraction)
    if not all((Path(args.data) / "ImageSets" / f"{n}.txt").exists() for n in (labeled, dev)):
        make_split(Path(args.data), args.fraction, args.seed, dev_fraction=args.dev_fraction)
    return labeled, unlabeled, dev


def stand_in_base(args: argparse.Namespace) -> ExperimentConfig:
    """The camera stand-in's recipe: the config with --camera-set, never --set (it trains from
    scratch; --set is for the runs that start from it, a fine-tuning rate, say)."""
    return apply_overrides(load_config(args.config), args.camera_set)


def ssl_config(base: ExperimentConfig, method: str, args: argparse.Namespace, out: Path):
    """A teacher-student run's config: the method's [ssl] settings from the pre-trained run, the
    [ssl] stage's schedule (`teacher_student_config`: constant rates after a warm-up) with
    --ssl-steps and the pre-training rates x --ssl-lr-factor where given, scored on dev halfway
    and at the end."""
    config = apply_overrides(base, METHODS[method]).replace("ssl", pretrained=str(out / "pretrain"))
    if method == "every-label":
        config = config.replace("data", train_split=every_label_split(args))
    stage = {} if args.ssl_steps is None else {"steps": args.ssl_steps}
    if args.ssl_lr_factor is not None:
        factor = args.ssl_lr_factor
        stage.update(lr_2d=base.train.lr_2d * factor, lr_3d=base.train.lr_3d * factor)
    config = teacher_student_config(config.replace("ssl", **stage))
    steps = config.train.steps
    return config.replace(
        "train", eval_every=max(steps // 2, 1),
        checkpoint_every=min(base.train.checkpoint_every, steps),
    )  # fmt: skip


def learning_curve(run_dir: Path) -> list[dict]:
    """The dev evaluations a run logged: step, 2D and 3D moderate AP per class and mAP."""
    return [
        {"step": step, **{m: evaluation[m] for m in ("2d", "3d")}}
        for step, evaluation in run_evaluations(run_dir).items()
    ]


def as_labels(
    names: list[str], boxes_3d: np.ndarray, boxes_2d: np.ndarray, scores: np.ndarray
) -> Labels:
    n = len(names)
    return Labels(
        names=np.array(names, dtype=object), boxes_2d=Boxes2D(boxes_2d.reshape(n, 4)),
        boxes_3d=Boxes3D(boxes_3d.reshape(n, 7)), truncated=np.zeros(n),
        occluded=np.zeros(n, dtype=np.int64), alpha=np.zeros(n), scores=scores,
    )  # fmt: skip


def pseudo_label_sets(
    det_2d: Detections,
    det_3d: Detections,
    sample,
    classes: tuple[str, ...],
    config: ExperimentConfig,
) -> dict[str, Labels]:
    """The same teacher detections filtered by each method's rule, as Labels rows: 3D rows carry
    zero 2D boxes and 2D rows zero 3D boxes, so each counts for its own modality only."""
    ssl = config.ssl
    size = sample.image_transform.original_size
    in_view = boxes_touching_image(det_3d.boxes, sample.calib, size)
    confident_3d = confident_detections(det_3d[in_view], ssl.tau_3d)
    confident_2d = confident_detections(det_2d, ssl.tau_2d)
    policy = MatchingPolicy.from_config(ssl).with_overrides(outside_view_fallback=False)
    matched = match_detections(det_3d, det_2d, sample.calib, size, policy)
    pairs = matched.matched  # the 2D labels: LiDAR-only rows have none
    return {
        "confidence": modality_labels(
            (confident_3d.boxes, confident_3d.classes, confident_3d.scores),
            (confident_2d.boxes, confident_2d.classes, confident_2d.scores), classes,
        ),
        "detmatch": modality_labels(
            (matched.boxes_3d, matched.class_3d, matched.score_3d),
            (matched.boxes_2d[pairs], matched.class_2d[pairs], matched.score_2d[pairs]), classes,
        ),
    }  # fmt: skip


def modality_labels(rows_3d: tuple, rows_2d: tuple, classes: tuple[str, ...]) -> Labels:
    """3D and 2D pseudo-labels, each (boxes, class ids, scores), as one Labels: 3D rows carry
    zero 2D boxes and 2D rows zero 3D boxes, so each counts for its own modality only."""
    (b3, c3, s3), (b2, c2, s2) = rows_3d, rows_2d
    names = [classes[c] for c in c3] + [classes[c] for c in c2]
    boxes_3d = np.concatenate([b3.reshape(-1, 7), np.zeros((len(c2), 7))])
    boxes_2d = np.concatenate([np.zeros((len(c3), 4)), b2.reshape(-1, 4)])
    return as_labels(names, boxes_3d, boxes_2d, np.concatenate([s3, s2]))


# Figure 4: a ground-truth object counts as found by a modality when a confident (score > 0.3)
# detection of its class overlaps it: 2D IoU >= 0.5; bird's-eye-view IoU >= these.
FOUND_SCORE = 0.3
FOUND_BEV_IOU = {"Car": 0.5, "Pedestrian": 0.25, "Cyclist": 0.25}


def found_by(det_2d: Detections, det_3d: Detections, labels: Labels, classes) -> list[tuple]:
    """(class, occlusion, found in 2D, found in 3D) of each labeled object of the classes."""
    rows = []
    for class_id, name in enumerate(classes):
        objects = np.flatnonzero(labels.names == name)
        if not len(objects):
            continue
        d2 = det_2d[(det_2d.classes == class_id) & (det_2d.scores > FOUND_SCORE)]
        d3 = det_3d[(det_3d.classes == class_id) & (det_3d.scores > FOUND_SCORE)]
        iou_2d = pairwise_iou_2d(labels.boxes_2d.xyxy[objects], d2.boxes)
        iou_3d = pairwise_iou_bev(labels.boxes_3d.data[objects], d3.boxes)
        bev_threshold = FOUND_BEV_IOU.get(name, 0.5)
        for k, row in enumerate(objects):
            in_2d = bool(len(d2)) and iou_2d[k].max() >= 0.5
            in_3d = bool(len(d3)) and iou_3d[k].max() >= bev_threshold
            rows.append((name, int(labels.occluded[row]), in_2d, in_3d))
    return rows


def complementarity(rows: list[tuple], classes) -> dict:
    """Recall per class and occlusion level (0, 1, 2) for 2D, 3D, either and both."""
    table: dict = {}
    for name in classes:
        for level in (0, 1, 2):
            hits = [(f2, f3) for c, occ, f2, f3 in rows if c == name and occ == level]
            if not hits:
                continue
            found = np.array(hits, dtype=bool)
            table.setdefault(name, {})[str(level)] = {
                "objects": len(hits), "2d": float(found[:, 0].mean()),
                "3d": float(found[:, 1].mean()), "either": float(found.any(axis=1).mean()),
                "both": float(found.all(axis=1).mean()),
            }  # fmt: skip
    return table


def draw_figure4(table: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(table)
    figure, axes = plt.subplots(1, len(names), figsize=(4 * len(names), 3.6), dpi=110)
    for axis, name in zip(np.atleast_1d(axes), names, strict=True):
        levels = sorted(table[name], key=int)
        x = np.arange(len(levels))
        for offset, key, colour in ((-0.2, "2d", "tab:blue"), (0.2, "3d", "tab:orange")):
            axis.bar(x + offset, [table[name][lv][key] for lv in levels], 0.4, label=key.upper(),
                     color=colour)  # fmt: skip
        axis.plot(x, [table[name][lv]["either"] for lv in levels], "k.--", label="either")
        axis.set_xticks(x, [f"occl. {lv}\n({table[name][lv]['objects']})" for lv in levels])
        axis.set_ylim(0, 1)
        axis.set_title(f"{name}: recall of confident detections")
        axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(out)


def draw_occlusion_curves(curves: dict, out: Path) -> dict:
    """The paper's Figure 4: P/R curves of both modalities per class, one line style per
    occlusion level. Returns {class: {level: {"objects", "2d", "3d"}}}, AP R40 in percent."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table: dict = {}
    names = list(curves)
    figure, axes = plt.subplots(1, len(names), figsize=(4.4 * len(names), 4), dpi=110)
    for axis, name in zip(np.atleast_1d(axes), names, strict=True):
        for modality, colour in (("2d", "tab:blue"), ("3d", "tab:orange")):
            for level, style in zip(OCCLUSION_LEVELS, ("-", "--", ":"), strict=True):
                curve = curves[name][modality][level]
                row = table.setdefault(name, {}).setdefault(str(level), {"objects": curve.objects})
                row[modality] = curve.average_precision()
                precision, recall = curve.precision_recall()
                label = f"{modality.upper()} occl. {level}: AP {row[modality]:.0f}"
                axis.plot(recall, precision, style, color=colour, label=label)
        axis.set_xlim(0, 1)
        axis.set_ylim(0, 1.02)
        axis.set_xlabel("recall")
        axis.set_ylabel("precision")
        axis.set_title(f"{name}: image-plane P/R by occlusion")
        axis.legend(fontsize=6.5, loc="lower left")
    figure.tight_layout()
    figure.savefig(out)
    return table


def teacher_frames(
    loaded: LoadedDetectors, dataset: FrameDataset, max_frames: int, workers: int = 0
) -> Iterator[tuple[Sample, Detections, Detections, Labels]]:
    """(sample, 2D detections, 3D detections, the frame's labels) of the dataset's first
    max_frames frames, by a loaded run's detectors (its teachers)."""
    count = min(max_frames, len(dataset))
    loader = torch.utils.data.DataLoader(
        torch.utils.data.Subset(dataset, range(count)),
        batch_size=4,
        collate_fn=collate,
        num_workers=workers,
    )
    for batch in loader:
        detections = predict_batch(loaded.model_2d, loaded.model_3d, batch)
        for sample, (det_2d, det_3d) in zip(batch.samples, detections, strict=True):
            yield sample, det_2d, det_3d, dataset.kitti.load_frame(sample.frame_id).labels


def add_occlusion_curves(
    curves: dict,
    det_2d: Detections,
    view: Detections,
    projected: np.ndarray,
    labels: Labels,
    classes,
) -> None:
    """One frame into the paper's Figure 4 curves, curves[class][modality][level]: every 2D
    detection, and every 3D detection touching the image (`view`, its boxes `projected` into
    it), against the annotated 2D boxes (detmatch.eval.occlusion)."""
    for class_id, name in enumerate(classes):
        rows, levels = object_levels(labels.names, labels.occluded, name)
        objects = labels.boxes_2d.xyxy[rows]
        own_2d, own_3d = det_2d.classes == class_id, view.classes == class_id
        for modality, boxes, scores in (
            ("2d", det_2d.boxes[own_2d], det_2d.scores[own_2d]),
            ("3d", projected[own_3d], view.scores[own_3d]),
        ):
            by_level = curves.setdefault(name, {}).setdefault(modality, {})
            for level in OCCLUSION_LEVELS:
                by_level.setdefault(level, LevelCurve()).add_frame(
                    boxes, scores, objects, levels, level
                )


def analyse_teacher(
    checkpoint: Path, config: ExperimentConfig, max_frames: int
) -> tuple[dict, np.ndarray, dict, dict]:
    """Pseudo-label quality of the pre-trained teacher under both rules; Figure 3's points:
    rows (true 3D IoU, max class score, best matching cost) of in-view 3D detections;
    Figure 4's table: 2D and 3D recall per class and occlusion level; and the paper's Figure 4
    curves: curves[class][modality][level], a LevelCurve in the image plane."""
    loaded = load_detectors(checkpoint)
    data = config.data
    dataset = FrameDataset(
        data.root, config.ssl.unlabeled_split, data.classes, data.image_size, loaded.model_3d.grid
    )
    pseudo: dict[str, list[Labels]] = {"confidence": [], "detmatch": []}
    ground_truth, points, found, curves = [], [], [], {}
    for sample, det_2d, det_3d, labels in teacher_frames(
        loaded, dataset, max_frames, data.num_workers
    ):
        ground_truth.append(labels)
        found += found_by(det_2d, det_3d, labels, data.classes)
        for method, rows in pseudo_label_sets(det_2d, det_3d, sample, data.classes, config).items():
            pseudo[method].append(rows)
        size = sample.image_transform.original_size
        view = det_3d[boxes_touching_image(det_3d.boxes, sample.calib, size)]
        projected = project_boxes_to_image(view.boxes, sample.calib, size)
        add_occlusion_curves(curves, det_2d, view, projected, labels, data.classes)
        objects = np.isin(labels.names, data.classes)
        if len(view) == 0 or len(det_2d) == 0:
            continue
        iou = np.zeros(len(view))
        if objects.any():
            iou = pairwise_iou_3d(view.boxes, labels.boxes_3d.data[objects]).max(axis=1)
        cost = matching_cost(
            projected, view.probabilities, det_2d.boxes, det_2d.probabilities, size
        ).min(axis=1)
        points.append(np.column_stack([iou, view.scores, cost]))
    quality = {
        method: pseudo_label_quality(rows, ground_truth, data.classes, IOU_3D, IOU_2D)
        for method, rows in pseudo.items()
    }
    points = np.concatenate(points) if points else np.zeros((0, 3))
    return quality, points, complementarity(found, data.classes), curves


def draw_figure(points: np.ndarray, out: Path) -> dict[str, float]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import spearmanr

    iou, score, cost = points.T
    rho_score = float(spearmanr(iou, score).statistic)
    rho_cost = float(spearmanr(iou, -cost).statistic)
    figure, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=110)
    axes[0].scatter(score, iou, s=4, alpha=0.4)
    axes[0].set_xlabel("max class score (3D teacher)")
    axes[0].set_title(f"IoU vs confidence (Spearman {rho_score:.2f})")
    axes[1].scatter(cost, iou, s=4, alpha=0.4, color="tab:orange")
    axes[1].axvline(-1.5, color="grey", linestyle="--", label="tau_hung = -1.5")
    axes[1].set_xlabel("best 2D-3D matching cost")
    axes[1].set_title(f"IoU vs matching cost (Spearman {rho_cost:.2f} with -cost)")
    axes[1].legend()
    for axis in axes:
        axis.set_ylabel("true 3D IoU with ground truth")
        axis.set_ylim(0, 1)
    figure.tight_layout()
    figure.savefig(out)
    return {"spearman_iou_score": rho_score, "spearman_iou_negative_cost": rho_cost}


def evaluate_runs(
    runs: dict[str, Path], dataset: FrameDataset, classes: tuple[str, ...], context, workers: int
) -> dict[str, dict]:
    """Moderate R40 AP per class (2D, 3D, BEV) of each run's output models on a dataset."""
    results = {}
    for name, run in runs.items():
        loaded = load_detectors(run)
        loaded.model_2d.to(context.device)
        loaded.model_3d.to(context.device)
        metrics = evaluate_detectors(
            loaded.model_2d, loaded.model_3d, dataset, classes, num_workers=workers
        )
        results[name] = {k: metrics[k] for k in ("2d", "3d", "bev")}
    return results


def stand_in_figures(
    run: Path, base: ExperimentConfig, dev: FrameDataset, context, frames: int, figure: Path
) -> dict:
    """The camera stand-in before any pre-training, with the benchmark's own functions: its 2D
    moderate AP on dev, and Figure 4's 2D rows (image-plane AP by occlusion) over `frames`
    frames of the pool, drawn to `figure`."""
    classes = base.data.classes
    dev_2d = evaluate_runs({"stand-in": run}, dev, classes, context, base.data.num_workers)
    curves = analyse_teacher(run, base, frames)[3]
    occlusion = draw_occlusion_curves(curves, figure) if curves else {}
    return {
        "dev_2d": dev_2d["stand-in"]["2d"],
        "figure4_pr_2d": {name: {level: {"objects": r["objects"], "2d": r["2d"]}
                                 for level, r in levels.items()}
                          for name, levels in occlusion.items()},
    }  # fmt: skip


def stand_in_lines(run: Path, figures: dict, classes: tuple[str, ...], frames: int) -> list[str]:
    """The report's section on the stand-in (stand_in_figures)."""
    dev = figures["dev_2d"]
    lines = [f"## The 2D stand-in before pre-training ({run})", "",
             "| dev, 2D moderate R40 | " + " | ".join(classes) + " | mAP |",
             "|---|" + "---|" * (len(classes) + 1),
             "| stand-in | " + " | ".join(f"{dev[c]:.1f}" for c in classes)
             + f" | {dev['mAP']:.1f} |", "",
             f"Figure 4's 2D rows for it, {frames} pool frames (figure4_pr_stand_in.png):", "",
             "| class | occlusion | objects | 2D AP |", "|---|---|---|---|"]  # fmt: skip
    for name, levels in figures["figure4_pr_2d"].items():
        for level, r in levels.items():
            lines.append(f"| {name} | {level} | {r['objects']} | {r['2d']:.1f} |")
    return lines + [""]


def ap_table(results: dict[str, dict], modality: str, classes: tuple[str, ...]) -> list[str]:
    """Markdown rows: AP per class, mAP, gain over the better labeled-only baseline."""
    baselines = [results[b][modality]["mAP"] for b in BASELINES if b in results]
    reference = max(baselines) if baselines else 0.0
    rows = ["| method | " + " | ".join(classes) + " | mAP | gain |"]
    rows.append("|---|" + "---|" * (len(classes) + 2))
    for name, metrics in results.items():
        row = metrics[modality]
        gain = "" if name in BASELINES else f"{row['mAP'] - reference:+.1f}"
        cells = " | ".join(f"{row[c]:.1f}" for c in classes)
        rows.append(f"| {name} | {cells} | {row['mAP']:.1f} | {gain} |")
    return rows


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--config", default="configs/ssl_cpu.toml")
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--seed", type=int, default=0, help="split seed of the labeled subset")
    parser.add_argument("--fraction", type=float, default=0.05, help="labeled fraction of train")
    parser.add_argument("--dev-fraction", type=float, default=0.1, help="dev fraction of train")
    parser.add_argument(
        "--ssl-steps", type=int,
        help="teacher-student steps (default: the config's [ssl] steps; dev chose 1,200 over 600: "
        "BENCHMARKS.md, issue 14)",
    )  # fmt: skip
    parser.add_argument(
        "--ssl-lr-factor", type=float,
        help="teacher-student learning rates: pre-training's x this (default: the config's "
        "[ssl] lr_2d and lr_3d, 0.1x the pre-training's in configs/ssl_cpu.toml)",
    )  # fmt: skip
    parser.add_argument("--analysis-frames", type=int, default=200)
    parser.add_argument(
        "--methods",
        default="control,confidence,detmatch",
        help="comma-separated, from: " + ", ".join(METHODS) + " (empty: pre-training only)",
    )
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="config override for every run (repeatable)")  # fmt: skip
    parser.add_argument("--device", default="auto", choices=DEVICES)
    parser.add_argument("--workers", type=int, help="override [data] num_workers")
    parser.add_argument(
        "--train-only",
        action="store_true",
        help="stop after training (to train methods in parallel processes, then report once)",
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="train nothing: report the pre-trained run and the methods whose runs finished",
    )
    parser.add_argument("--skip-val", action="store_true",
                        help="score dev only (tuning: val is scored once, at the end)")  # fmt: skip
    parser.add_argument(
        "--camera-data",
        help="a separate synthetic set (another generator seed) whose every label pre-trains "
        "the 2D detector that every method starts from: the stand-in for the paper's COCO start "
        "(benchmarks/camera_init.py)",
    )
    parser.add_argument("--camera-run", help="the stand-in's run directory (default OUT/camera)")
    parser.add_argument("--camera-steps", type=int, default=camera_init.DEFAULT_STEPS)
    parser.add_argument("--camera-set", action="append", default=[],
                        metavar="SECTION.KEY=VALUE",
                        help="config override for the stand-in's run only (repeatable): it "
                        "trains from scratch on the config and these, not on --set, which is "
                        "for the runs that start from it (a fine-tuning rate, say)")  # fmt: skip
    args = parser.parse_args()
    methods = [m for m in args.methods.split(",") if m]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        parser.error(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
    out = Path(args.out)
    labeled, unlabeled, dev = splits(args)
    base = apply_overrides(load_config(args.config), args.set)
    base = base.replace("data", root=args.data, train_split=labeled, val_split=dev)
    base = base.replace("ssl", unlabeled_split=unlabeled)
    if args.workers is not None:
        base = base.replace("data", num_workers=args.workers)
    classes = base.data.classes
    stage = ssl_config(base, "control", args, out).train  # every method's steps and rates
    context = init_distributed(args.device)
    timings = {}
    world, resolution = read_world(Path(args.data)), read_resolution(Path(args.data))
    camera_run = Path(args.camera_run) if args.camera_run else out / "camera"
    if args.camera_data:
        camera_init.check_disjoint(Path(args.camera_data), Path(args.data))
        started = time.perf_counter()
        start_2d = camera_init.train_camera_init(
            stand_in_base(args), Path(args.camera_data), camera_run, context, args.camera_steps
        )
        timings["camera"] = time.perf_counter() - started
        base = base.replace("train", init_2d=str(start_2d))
    if args.report_only:
        for method in [m for m in methods if not finished(out / m, stage.steps)]:
            print(f"{method}: run unfinished, left out of the report", file=sys.stderr)
            methods.remove(method)
    else:
        timings["pretrain"] = train_stage(SupervisedTrainer, base, out / "pretrain", context)
        for method in methods:
            config = ssl_config(base, method, args, out)
            trainer = trainer_type(config.ssl.method)
            timings[method] = train_stage(trainer, config, out / method, context)
    if args.train_only:
        print(json.dumps({"train_wall_s": timings}))
        return

    started = time.perf_counter()
    grid = build_detectors(base)[1].grid
    runs = {"labeled-only": out / "pretrain", **{m: out / m for m in methods}}
    workers = base.data.num_workers
    scored = {"dev": dev} if args.skip_val else {"dev": dev, "val": "val"}
    datasets = {split: FrameDataset(args.data, name, classes, base.data.image_size, grid)
                for split, name in scored.items()}  # fmt: skip
    results = {
        split: evaluate_runs(runs, dataset, classes, context, workers)
        for split, dataset in datasets.items()
    }
    quality, points, recall, curves = analyse_teacher(out / "pretrain", base, args.analysis_frames)
    correlation = draw_figure(points, out / "figure3.png") if len(points) else {}
    if recall:
        draw_figure4(recall, out / "figure4.png")
    occlusion_ap = draw_occlusion_curves(curves, out / "figure4_pr.png") if curves else {}
    stand_in = {}
    if args.camera_data:
        figure = out / "figure4_pr_stand_in.png"
        stand_in = stand_in_figures(camera_run, base, datasets["dev"], context,
                                    args.analysis_frames, figure)  # fmt: skip
    timings["report"] = time.perf_counter() - started

    lines = [f"# Semi-supervised benchmark, seed {args.seed}", ""]
    rendered = f" at {resolution} camera resolution" if resolution else ""
    lines += [f"World {world or 'not synthetic'}{rendered} ({args.data}); labeled {labeled}, "
              f"unlabeled {unlabeled}, dev {dev}; config {args.config}"]  # fmt: skip
    if args.camera_data:
        lines += [f"2D detector starts from {base.train.init_2d} (every label of "
                  f"{args.camera_data}: the COCO stand-in)"]  # fmt: skip
    lines += [f"{' '.join(args.set)}; {stage.steps} teacher-student steps at rates "
              f"{stage.lr_2d:g} (2D) and {stage.lr_3d:g} (3D).", ""]  # fmt: skip
    for split in results:
        for modality in ("3d", "2d"):
            lines += [f"## {split}: {modality.upper()} AP (moderate, R40)", ""]
            lines += ap_table(results[split], modality, classes) + [""]
    lines += [
        "## Pre-training learning curve on dev (mAP)",
        "",
        "| step | 2D | 3D |",
        "|---|---|---|",
    ]
    curve = learning_curve(out / "pretrain")
    lines += [f"| {p['step']} | {p['2d']['mAP']:.1f} | {p['3d']['mAP']:.1f} |" for p in curve]
    lines += ["", f"## Pseudo-labels of the pre-trained teacher, {args.analysis_frames} frames", ""]
    lines += ["| rule | modality | class | precision | recall | F1 | labels | objects |"]
    lines += ["|---|---|---|---|---|---|---|---|"]
    for method, per_class in quality.items():
        for modality in ("3d", "2d"):
            for name in classes:
                q = per_class[name][modality]
                cells = [method, modality, name]
                cells += [f"{value:.3f}" for value in pooled_precision_recall_f1([q])]
                cells += [str(q["num_pseudo"]), str(q["num_gt"])]
                lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"Figure 3: figure3.png ({len(points)} 3D teacher boxes), Spearman {correlation}"]
    lines += ["", "## Figure 4: recall of the pre-trained detectors by occlusion (figure4.png)", ""]
    lines += [
        "| class | occlusion | objects | 2D | 3D | either | both |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, levels in recall.items():
        for level, r in levels.items():
            lines.append(f"| {name} | {level} | {r['objects']} | {r['2d']:.2f} | {r['3d']:.2f} | "
                         f"{r['either']:.2f} | {r['both']:.2f} |")  # fmt: skip
    lines += ["", "## Figure 4 as in the paper: image-plane AP (R40, IoU 0.5) by occlusion "
              "(figure4_pr.png)", "", "| class | occlusion | objects | 2D AP | 3D AP |",
              "|---|---|---|---|---|"]  # fmt: skip
    for name, levels in occlusion_ap.items():
        for level, r in levels.items():
            lines.append(f"| {name} | {level} | {r['objects']} | {r['2d']:.1f} | {r['3d']:.1f} |")
    if stand_in:
        lines += [""] + stand_in_lines(camera_run, stand_in, classes, args.analysis_frames)
    lines += ["", f"Wall seconds: {json.dumps({k: round(v) for k, v in timings.items()})}"]
    lines += ["", f"rerun: {rerun('ssl_benchmark')}"]
    report = "\n".join(lines) + "\n"
    (out / "report.md").write_text(report)
    print(report)
    summary = {
        "seed": args.seed,
        "world": world,
        "resolution": resolution,
        "init_2d": base.train.init_2d,
        "stand_in": stand_in,
        "splits": {"labeled": labeled, "unlabeled": unlabeled, "dev": dev},
        "results": results,
        "learning_curve": curve,
        "pseudo_label_quality": quality,
        "figure3": correlation,
        "figure4": recall,
        "figure4_pr": occlusion_ap,
        "train_wall_s": timings,
        "command": rerun("ssl_benchmark"),
    }
    (out / "ssl_benchmark.json").write_text(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
