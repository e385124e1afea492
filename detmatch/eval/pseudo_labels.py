"""Pseudo-label quality: precision and recall of pseudo-labels against hidden ground truth.

Per class and modality ("3d": exact rotated 3D IoU of the LiDAR-frame `Labels.boxes_3d`;
"2d": IoU of `Labels.boxes_2d`), frame by frame:

- pseudo-labels and ground truth of the class are taken by case-insensitive name; DontCare
  rows (and any other class) take no part. A row only counts for a modality where it has a box
  there: 3D boxes with all sizes > 0, 2D boxes with positive width and height (so 2D-only
  pseudo-labels, whose 3D rows are zeros, count for "2d" only, and vice versa);
- matching is greedy and one-to-one: pseudo-labels in descending score (file order when the
  labels carry no scores, stable for ties) each take the still unmatched ground-truth box of
  highest IoU, if that IoU >= the class's threshold;
- precision = TP / pseudo-labels, recall = TP / ground truth, each 0.0 when its denominator is
  0 (the counts say which).

There are no difficulty levels, neighbour classes or ignore regions: this measures how many of
the labels a student is trained on are right, and how many objects they cover.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from detmatch.eval.kitti_overlaps import frame_pairs
from detmatch.geometry import paired_iou_3d
from detmatch.structures import Labels

MODALITIES = ("3d", "2d")


def pseudo_label_quality(
    pseudo: Sequence[Labels],
    gt: Sequence[Labels],
    classes: Sequence[str],
    iou_thresholds_3d: Mapping[str, float],
    iou_thresholds_2d: Mapping[str, float],
) -> dict:
    """Precision / recall of per-frame pseudo-labels against per-frame ground truth.

    Returns {class: {"3d": {"precision", "recall", "tp", "num_pseudo", "num_gt",
    "iou_threshold"}, "2d": {...}}} with plain floats and ints (JSON-ready).
    """
    if len(pseudo) != len(gt):
        raise ValueError(f"{len(pseudo)} pseudo-label frames but {len(gt)} ground-truth frames")
    thresholds = {
        "3d": {c: _threshold(iou_thresholds_3d, c, "3D") for c in classes},
        "2d": {c: _threshold(iou_thresholds_2d, c, "2D") for c in classes},
    }
    pseudo_rows, gt_rows = _FrameRows(pseudo), _FrameRows(gt)
    results: dict = {c: {} for c in classes}
    for modality in MODALITIES:
        ious, block_offsets = _same_frame_ious(pseudo_rows, gt_rows, modality)
        for name in classes:
            counts = _match_class(
                pseudo_rows, gt_rows, ious, block_offsets, name.lower(), modality,
                thresholds[modality][name],
            )  # fmt: skip
            tp, num_pseudo, num_gt = counts
            results[name][modality] = {
                "precision": tp / num_pseudo if num_pseudo else 0.0,
                "recall": tp / num_gt if num_gt else 0.0,
                "tp": tp,
                "num_pseudo": num_pseudo,
                "num_gt": num_gt,
                "iou_threshold": thresholds[modality][name],
            }
    return results


def pooled_precision_recall_f1(rows: Sequence[Mapping]) -> tuple[float, float, float]:
    """Precision, recall and F1 of pseudo_label_quality rows (one class and modality, e.g. of
    several runs) with their true positives, pseudo-labels and objects summed."""
    tp = sum(row["tp"] for row in rows)
    precision = tp / max(sum(row["num_pseudo"] for row in rows), 1)
    recall = tp / max(sum(row["num_gt"] for row in rows), 1)
    return precision, recall, 2 * precision * recall / max(precision + recall, 1e-12)


class _FrameRows:
    """Labels of many frames concatenated: names (N,) lower-case; boxes_2d (N, 4) pixels;
    boxes_3d (N, 7) LiDAR frame; rank (N,) sort key, minus the score (0 without scores);
    offsets (F + 1,): frame f owns rows offsets[f]:offsets[f + 1]."""

    def __init__(self, frames: Sequence[Labels]) -> None:
        counts = np.array([len(labels) for labels in frames], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        present = [labels for labels in frames if len(labels)]
        if not present:
            self.names = np.zeros(0, dtype=str)
            self.boxes_2d, self.boxes_3d = np.zeros((0, 4)), np.zeros((0, 7))
            self.rank = np.zeros(0)
            return
        self.names = np.char.lower(np.concatenate([labels.names for labels in present]).astype(str))
        self.boxes_2d = np.concatenate([labels.boxes_2d.xyxy for labels in present])
        self.boxes_3d = np.concatenate([labels.boxes_3d.data for labels in present])
        self.rank = np.concatenate(
            [np.zeros(len(x)) if x.scores is None else -x.scores for x in present]
        )

    def has_box(self, modality: str) -> np.ndarray:
        if modality == "3d":
            return np.all(self.boxes_3d[:, 3:6] > 0, axis=1)
        x1, y1, x2, y2 = self.boxes_2d.T
        return (x2 > x1) & (y2 > y1)


def _same_frame_ious(
    pseudo: _FrameRows, gt: _FrameRows, modality: str
) -> tuple[np.ndarray, np.ndarray]:
    """(P,) IoU of every same-frame, same-name (pseudo, gt) pair in frame blocks, (F + 1,)."""
    block_offsets, p_index, g_index = frame_pairs(pseudo.offsets, gt.offsets)
    ious = np.zeros(block_offsets[-1])
    usable = (
        (pseudo.names[p_index] == gt.names[g_index])
        & pseudo.has_box(modality)[p_index]
        & gt.has_box(modality)[g_index]
    )
    pairs = np.flatnonzero(usable)
    if modality == "3d":
        ious[pairs] = paired_iou_3d(pseudo.boxes_3d[p_index[pairs]], gt.boxes_3d[g_index[pairs]])
    else:
        a, b = pseudo.boxes_2d[p_index[pairs]], gt.boxes_2d[g_index[pairs]]
        iw = np.clip(np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0]), 0, None)
        ih = np.clip(np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1]), 0, None)
        inter = iw * ih
        area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
        area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
        ious[pairs] = inter / (area_a + area_b - inter)
    return ious, block_offsets


def _match_class(
    pseudo: _FrameRows,
    gt: _FrameRows,
    ious: np.ndarray,
    block_offsets: np.ndarray,
    name: str,
    modality: str,
    threshold: float,
) -> tuple[int, int, int]:
    """Greedy one-to-one matching of one class in every frame -> (TP, #pseudo, #gt)."""
    pseudo_mask = (pseudo.names == name) & pseudo.has_box(modality)
    gt_mask = (gt.names == name) & gt.has_box(modality)
    tp = 0
    for f in range(len(pseudo.offsets) - 1):
        p0, p1, g0, g1 = pseudo.offsets[f], pseudo.offsets[f + 1], gt.offsets[f], gt.offsets[f + 1]
        rows = np.flatnonzero(pseudo_mask[p0:p1])
        cols = np.flatnonzero(gt_mask[g0:g1])
        if rows.size == 0 or cols.size == 0:
            continue
        block = ious[block_offsets[f] : block_offsets[f + 1]].reshape(p1 - p0, g1 - g0)
        block = block[np.ix_(rows, cols)]
        taken = np.zeros(cols.size, dtype=bool)
        for r in np.argsort(pseudo.rank[p0:p1][rows], kind="stable"):
            candidates = np.where(taken, -1.0, block[r])
            best = int(np.argmax(candidates))
            if candidates[best] >= threshold:
                taken[best] = True
                tp += 1
    return tp, int(pseudo_mask.sum()), int(gt_mask.sum())


def _threshold(thresholds: Mapping[str, float], name: str, kind: str) -> float:
    if name in thresholds:
        return float(thresholds[name])
    for key, value in thresholds.items():
        if key.lower() == name.lower():
            return float(value)
    raise ValueError(f"no {kind} IoU threshold for class {name!r} (have {sorted(thresholds)})")
