"""The paper's Figure 4: each modality's precision / recall by occlusion level.

Both detectors are judged in one space, the image: 2D detections as they are, 3D detections
projected (`detmatch.geometry.project_boxes_to_image`). A detection is right when its box
overlaps a labeled object of its class at 2D IoU >= the threshold.

For occlusion level L of a class, the class's objects at the other levels, and any box passed
as ignore-only (level -1: DontCare regions, a neighbour class such as Van for Car), are
ignored: a detection on one counts neither as a hit nor as a false positive, as KITTI does
with objects outside a difficulty. So every level's curve carries the same false positives,
and a level's recall is the share of its own objects found.

Matching is greedy and one-to-one, frame by frame: detections in descending score (stable for
ties) each take the still unmatched object of the level with the highest IoU; a detection
without one but overlapping an ignored box (IoU >= the threshold) is dropped; any other is a
false positive.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from detmatch.eval.kitti import NEIGHBOUR_CLASS
from detmatch.geometry import pairwise_iou_2d

IGNORE_LEVEL = -1
LEVELS = (0, 1, 2)
RECALL_POINTS = np.linspace(1 / 40, 1.0, 40)


def object_levels(
    names: np.ndarray, occluded: np.ndarray, name: str
) -> tuple[np.ndarray, np.ndarray]:
    """A frame's label rows that take part for class `name`, and their levels: the class's
    objects at their occlusion level (0, 1, 2; IGNORE_LEVEL for unknown), its neighbour class
    (Van for Car, Person_sitting for Pedestrian) and DontCare at IGNORE_LEVEL."""
    lower = np.char.lower(np.asarray(names, dtype=str))
    own = lower == name.lower()
    others = (lower == "dontcare") | (lower == NEIGHBOUR_CLASS.get(name.lower(), "dontcare"))
    rows = np.flatnonzero(own | others)
    occluded = np.asarray(occluded)[rows]
    known = own[rows] & np.isin(occluded, LEVELS)
    return rows, np.where(known, occluded, IGNORE_LEVEL).astype(np.int64)


@dataclass
class LevelCurve:
    """Scored detections of one (class, modality, occlusion level), pooled over frames."""

    scores: list[np.ndarray] = field(default_factory=list)
    hits: list[np.ndarray] = field(default_factory=list)
    objects: int = 0

    def add_frame(
        self,
        boxes: np.ndarray,
        scores: np.ndarray,
        objects: np.ndarray,
        levels: np.ndarray,
        level: int,
        iou_threshold: float = 0.5,
    ) -> None:
        """(N, 4) detection boxes, (N,) scores; (M, 4) object boxes, (M,) their occlusion
        levels (IGNORE_LEVEL for ignore-only boxes); the level this curve counts."""
        kept_scores, hits = match_level(boxes, scores, objects, levels, level, iou_threshold)
        self.scores.append(kept_scores)
        self.hits.append(hits)
        self.objects += int(np.sum(np.asarray(levels) == level))

    def precision_recall(self) -> tuple[np.ndarray, np.ndarray]:
        """Precision and recall after each detection, in descending score."""
        scores = np.concatenate(self.scores) if self.scores else np.zeros(0)
        hits = np.concatenate(self.hits) if self.hits else np.zeros(0, dtype=bool)
        order = np.argsort(-scores, kind="stable")
        true_positives = np.cumsum(hits[order])
        precision = true_positives / np.arange(1, len(order) + 1)
        recall = true_positives / max(self.objects, 1)
        return precision, recall

    def average_precision(self) -> float:
        """AP in percent over 40 recall points (KITTI's R40): the mean, over recall r = 1/40 ..
        1, of the best precision at a recall >= r (0 where r is never reached)."""
        precision, recall = self.precision_recall()
        best = [precision[recall >= r].max() if np.any(recall >= r) else 0.0 for r in RECALL_POINTS]
        return float(np.mean(best) * 100.0)


def match_level(
    boxes: np.ndarray,
    scores: np.ndarray,
    objects: np.ndarray,
    levels: np.ndarray,
    level: int,
    iou_threshold: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """One frame's detections against its objects, counting objects at `level` (see the
    module docstring). Returns (K,) scores and (K,) hit flags of the detections not dropped."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    levels = np.asarray(levels).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    iou = pairwise_iou_2d(np.asarray(boxes).reshape(-1, 4)[order], objects)
    counted = levels == level
    taken = np.zeros(len(levels), dtype=bool)
    kept, hits = [], []
    for row, detection in enumerate(order):
        overlaps = iou[row] >= iou_threshold
        candidates = overlaps & counted & ~taken
        if candidates.any():
            taken[np.argmax(np.where(candidates, iou[row], -1.0))] = True
            kept.append(detection)
            hits.append(True)
        elif not (overlaps & ~counted).any():
            kept.append(detection)
            hits.append(False)
    return scores[np.asarray(kept, dtype=np.int64)], np.asarray(hits, dtype=bool)
