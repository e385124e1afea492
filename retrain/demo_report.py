"""The report directory of `detmatch demo`: report.md and its pictures.

REPORT/report.md            the tables: labeled-only vs DetMatch, serving, the round
REPORT/demo.json            every figure of the run
REPORT/curves.png           training losses of pre-training, DetMatch and the round
REPORT/figure3.png          the pre-trained 3D teacher's boxes: true IoU against their
                            score and against their best 2D-3D matching cost (as the
                            paper's Figure 3)
REPORT/frames/ID.png        served labels (dashed) over the synthetic ground truth (solid),
                            image above bird's-eye view
REPORT/per_class_ap.png     the round's two models, per class (from the round's report)
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from detmatch.files import atomic_write_bytes
from retrain.demo_results import DemoResults, results_json
from retrain.report import REPORT_JSON, ap_table, data_table, figure_png
from serving.manifest import GateFigures, RoundData

MODALITIES = (("3d", "3D"), ("2d", "2D"))
PICTURES = 3


def verdict(results: DemoResults) -> str:
    """Plainly: did DetMatch beat labeled-only (moderate mAP on val), per modality."""
    before, after = results.labeled_only, results.detmatch
    beat = [label for key, label in MODALITIES if after[key]["mAP"] > before[key]["mAP"]]
    lost = [label for key, label in MODALITIES if label not in beat]
    numbers = "; ".join(
        f"{label} mAP {after[key]['mAP']:.1f} vs {before[key]['mAP']:.1f} "
        f"({signed(after[key]['mAP'] - before[key]['mAP'])})"
        for key, label in MODALITIES
    )
    size = results.size
    where = (
        f"at this size ({results.splits['num_labeled']} labeled and "
        f"{results.splits['num_unlabeled']} unlabeled frames, {size.detmatch_steps} DetMatch "
        "steps)"
    )
    if len(beat) == len(MODALITIES):
        head = f"DetMatch beat labeled-only in both 2D and 3D {where}"
    elif not beat:
        head = f"DetMatch did not beat labeled-only in 2D or 3D {where}"
    else:
        head = f"DetMatch beat labeled-only in {beat[0]} but not in {lost[0]} {where}"
    return f"{head}: {numbers} (DetMatch vs labeled-only, moderate R40 on val)."


def signed(gain: float) -> str:
    """A gain to one decimal with its sign; one that rounds to zero is 0.0 (never -0.0)."""
    rounded = round(gain, 1)
    return "0.0" if rounded == 0 else f"{rounded:+.1f}"


def _ap_rows(results: DemoResults) -> list[str]:
    rows = ["| modality | class | labeled-only | DetMatch | gain |", "|---|---|---|---|---|"]
    for key, label in (*MODALITIES, ("bev", "BEV")):
        before, after = results.labeled_only[key], results.detmatch[key]
        for name in [k for k in before if k != "mAP"] + ["mAP"]:
            cell = f"**{name}**" if name == "mAP" else name
            rows.append(
                f"| {label} | {cell} | {before[name]:.1f} | {after[name]:.1f} | "
                f"{signed(after[name] - before[name])} |"
            )
    return rows


def curves_figure(runs: dict[str, Path]):
    """A matplotlib Figure: loss_2d and loss_3d against the step of each run's metrics.jsonl;
    a log axis labelled with plain numbers where the losses span a decade, whole steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

    plain = FuncFormatter(lambda value, _: f"{value:g}")
    figure, axes = plt.subplots(1, len(runs), figsize=(5 * len(runs), 3.6), dpi=100)
    for axis, (name, run) in zip(np.atleast_1d(axes), runs.items(), strict=True):
        records = []
        metrics = run / "metrics.jsonl"
        if metrics.is_file():
            records = [json.loads(line) for line in metrics.read_text().splitlines() if line]
        records = [r for r in records if "loss_2d" in r]
        steps = [r["step"] for r in records]
        for key, colour in (("loss_2d", "tab:orange"), ("loss_3d", "tab:blue")):
            axis.plot(steps, [r[key] for r in records], label=key, color=colour)
        axis.set_title(name)
        axis.set_xlabel("step")
        losses = [r[key] for r in records for key in ("loss_2d", "loss_3d") if r[key] > 0]
        if losses and max(losses) >= 10 * min(losses):  # a decade or more: log, 1-2-5 ticks
            axis.set_yscale("log")
            axis.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
            axis.yaxis.set_major_formatter(plain)
            axis.yaxis.set_minor_formatter(NullFormatter())
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
        axis.grid(alpha=0.3)
        axis.legend()
    figure.tight_layout()
    return figure


def plot_curves(runs: dict[str, Path]) -> bytes:
    """PNG bytes of `curves_figure`."""
    return figure_png(curves_figure(runs))


def figure3_points(checkpoint: Path, data_root: Path, split: str) -> np.ndarray:
    """Rows (true 3D IoU, max class score, best 2D-3D matching cost) of every in-view 3D
    detection of the checkpoint's models on a split (the benchmark's Figure 3)."""
    import torch

    from detmatch.data.dataset import FrameDataset, collate
    from detmatch.geometry import boxes_touching_image, pairwise_iou_3d, project_boxes_to_image
    from detmatch.inference import predict_batch
    from detmatch.matching import matching_cost
    from detmatch.models.build import load_detectors

    loaded = load_detectors(checkpoint)
    data = loaded.config.data
    dataset = FrameDataset(data_root, split, data.classes, data.image_size, loaded.model_3d.grid)
    loader = torch.utils.data.DataLoader(dataset, batch_size=4, collate_fn=collate)
    points = []
    for batch in loader:
        for sample, (det_2d, det_3d) in zip(
            batch.samples, predict_batch(loaded.model_2d, loaded.model_3d, batch), strict=True
        ):
            size = sample.image_transform.original_size
            view = det_3d[boxes_touching_image(det_3d.boxes, sample.calib, size)]
            if len(view) == 0 or len(det_2d) == 0:
                continue
            labels = dataset.kitti.load_frame(sample.frame_id).labels
            objects = np.isin(labels.names, data.classes)
            iou = np.zeros(len(view))
            if objects.any():
                iou = pairwise_iou_3d(view.boxes, labels.boxes_3d.data[objects]).max(axis=1)
            cost = matching_cost(
                project_boxes_to_image(view.boxes, sample.calib, size),
                view.probabilities,
                det_2d.boxes,
                det_2d.probabilities,
                size,
            ).min(axis=1)
            points.append(np.column_stack([iou, view.scores, cost]))
    return np.concatenate(points) if points else np.zeros((0, 3))


def plot_figure3(points: np.ndarray, tau_hung: float) -> tuple[bytes, dict[str, float]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import spearmanr

    iou, score, cost = points.T
    correlation = {}
    if len(points) > 2:
        correlation = {
            "spearman_iou_score": float(spearmanr(iou, score).statistic),
            "spearman_iou_negative_cost": float(spearmanr(iou, -cost).statistic),
        }
    figure, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=100)
    axes[0].scatter(score, iou, s=5, alpha=0.5)
    axes[0].set_xlabel("max class score (3D teacher)")
    axes[0].set_title("true IoU vs confidence")
    axes[1].scatter(cost, iou, s=5, alpha=0.5, color="tab:orange")
    axes[1].axvline(tau_hung, color="grey", linestyle="--", label=f"tau_hung = {tau_hung:g}")
    axes[1].set_xlabel("best 2D-3D matching cost")
    axes[1].set_title("true IoU vs matching cost")
    axes[1].legend()
    for axis in axes:
        axis.set_ylabel("true 3D IoU with ground truth")
        axis.set_ylim(0, 1)
    figure.tight_layout()
    return figure_png(figure), correlation


def draw_served_frames(results: DemoResults, report: Path) -> list[str]:
    """Pictures of a few frames the service labeled: its stored labels (KITTI rows, dashed)
    over the synthetic ground truth (solid). Returns the pictures' names."""
    from detmatch.data.kitti import KittiDataset, read_objects
    from detmatch.data.visualize import save_frame_picture
    from serving.store import export_store

    export = results.out / "logs" / "store_export"
    export_store(results.out / "store", export)
    source = KittiDataset(results.out / "new_frames")
    names = []
    for stored_id in results.served["ids"][:PICTURES]:
        frame = source.load_frame(stored_id.removeprefix("new-"))
        labels = read_objects(export / "training" / "label_2" / f"{stored_id}.txt")
        name = f"frames/{stored_id}.png"
        save_frame_picture(frame, report / name, predictions=labels)
        names.append(name)
    shutil.rmtree(export)
    return names


def write_demo_report(results: DemoResults) -> Path:
    """Write REPORT (see the module docstring) and return report.md's path."""
    out = results.out
    report = out / "report"
    report.mkdir(parents=True, exist_ok=True)
    runs = {
        "pre-training (labeled-only)": out / "runs" / "pretrain",
        "DetMatch": out / "runs" / "detmatch",
    }
    round_report = Path(results.round["report"]) if results.round.get("report") else None
    if round_report is not None:
        runs["retraining round"] = round_report.parent / "run"
        shutil.copyfile(round_report.parent / "per_class_ap.png", report / "per_class_ap.png")
    atomic_write_bytes(report / "curves.png", plot_curves(runs))
    from detmatch.config import load_config

    tau_hung = load_config(results.size.config).ssl.tau_hung
    points = figure3_points(out / "runs" / "pretrain", out / "data", "val")
    figure3, correlation = plot_figure3(points, tau_hung)
    atomic_write_bytes(report / "figure3.png", figure3)
    pictures = draw_served_frames(results, report)
    markdown = _markdown(results, pictures, len(points), correlation, round_report)
    atomic_write_bytes(report / "report.md", markdown.encode())
    summary = {**results_json(results), "figure3": correlation, "pictures": pictures}
    atomic_write_bytes(report / "demo.json", (json.dumps(summary, indent=2) + "\n").encode())
    return report / "report.md"


def _markdown(
    results: DemoResults,
    pictures: list[str],
    boxes: int,
    correlation: dict[str, float],
    round_report: Path | None,
) -> str:
    size, splits, served, swap = results.size, results.splits, results.served, results.swap
    timing = ", ".join(f"{k} {v:.0f} s" for k, v in results.timings.items() if k != "total")
    round_lines: list[str] = [f"**{results.round['message']}**"]
    if round_report is not None:
        summary = json.loads((round_report.parent / REPORT_JSON).read_text())
        parent = GateFigures(**summary["parent_figures"])
        candidate = GateFigures(**summary["candidate_figures"])
        round_lines += [
            "",
            f"The round trained {summary['steps']} DetMatch steps from version "
            f"{summary['parent_version']}'s checkpoint with the original frames and the "
            f"{served['frames']} stored frames in the unlabeled pool, then scored both models "
            f"on the same held-out gate (val); it promotes only if neither 2D nor 3D mAP drops "
            f"more than {summary['max_map_drop']:.1f} AP. Its own report: `{round_report}`.",
            "",
            ap_table(
                parent,
                candidate,
                f"parent {summary['parent_version']}",
                f"candidate {summary['version']}",
            ),
            "",
            data_table(RoundData(**summary["data"])),
            "",
            "![the round's per-class AP](per_class_ap.png)",
        ]
    lines = [
        f"# DetMatch demo (size {size.name})",
        "",
        f"**{verdict(results)}**",
        "",
        f"Wall time {results.timings.get('total', 0):.0f} s on {os.cpu_count()} CPU cores "
        f"(training device: {results.device}); {timing}.",
        "",
        "## Data",
        "",
        f"{size.frames} synthetic half-resolution frames (seed {results.seed}): "
        f"{splits['num_labeled']} labeled (`{splits['labeled']}`), {splits['num_unlabeled']} "
        f"unlabeled (`{splits['unlabeled']}`), {splits['num_val']} val (scored, never trained "
        f"on); {splits['num_new']} further unseen frames sent to the service. Config "
        f"`{size.config}`; {size.pretrain_steps} pre-training steps, {size.detmatch_steps} "
        "DetMatch steps.",
        "",
        "## Labeled-only vs DetMatch (val, moderate R40 AP, %)",
        "",
        *_ap_rows(results),
        "",
        "Labeled-only is the pre-trained model; DetMatch continued it for "
        f"{size.detmatch_steps} steps of labeled + unlabeled frames (the benchmark's "
        "comparison; BENCHMARKS.md reports larger runs and several seeds).",
        "",
        "## The service",
        "",
        f"`detmatch serve` (a separate process) labeled {served['frames']} unseen frames "
        f"through gRPC `LabelFrame` calls with version {', '.join(served['versions'])}: "
        f"{served['labels']} labels, {served['mean_latency_ms']:.0f} ms a call on average, "
        "each frame stored in the label store. Served labels (dashed) over the synthetic "
        "ground truth (solid):",
        "",
        *[f"![{name}]({name})" for name in pictures],
        "",
        "## Retraining round",
        "",
        *round_lines,
        "",
        f"After the round the running server answered with version {swap.get('answered_by')}: "
        "it polls the model repository and swapped to the promoted version by itself, without "
        f"a restart (the demo waited {swap.get('seconds', 0):.1f} s for it).",
        "",
        "## Training curves",
        "",
        "![losses of each run](curves.png)",
        "",
        "## Figure 3",
        "",
        f"{boxes} in-view 3D boxes of the pre-trained teacher on val: their true IoU against "
        "their confidence and against their best 2D-3D matching cost (the paper's Figure 3). "
        + (
            f"Spearman correlation of IoU with the score {correlation['spearman_iou_score']:.2f}"
            f", with the negated cost {correlation['spearman_iou_negative_cost']:.2f}."
            if correlation
            else ""
        ),
        "",
        "![IoU against score and matching cost](figure3.png)",
        "",
        "## Reproduce",
        "",
        f"    detmatch demo --size {size.name} --seed {results.seed} --out DIR",
        "",
    ]
    return "\n".join(lines)
