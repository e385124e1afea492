"""Flat per-frame object arrays and every frame's detection x ground-truth overlaps, batched.

All frames are concatenated so that the 2D, BEV and 3D overlaps of every (detection, ground
truth) pair of the same frame are computed in a few vectorised calls, not per pair in Python.
BEV and 3D IoU are exact (`detmatch.geometry.paired_bev_intersection`) on boxes in the upright
frame of `upright_boxes_from_camera`, a rotation of the camera frame, which keeps IoU.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from detmatch.data.kitti import KittiObjects
from detmatch.geometry import paired_bev_intersection, upright_boxes_from_camera


@dataclass(frozen=True)
class FlatObjects:
    """Rows of many frames, concatenated; frame f owns rows offsets[f]:offsets[f + 1].

    names: (N,) lower-case str; bbox: (N, 4) x1 y1 x2 y2 px; alpha, truncated: (N,);
    occluded: (N,) int64; boxes: (N, 7) upright-frame x y z l w h yaw (metres, radians;
    meaningless where has_3d is False); has_3d: (N,) bool; score: (N,) (0 for ground truth).
    """

    names: np.ndarray
    offsets: np.ndarray
    bbox: np.ndarray
    alpha: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    boxes: np.ndarray
    has_3d: np.ndarray
    score: np.ndarray

    @property
    def num(self) -> int:
        return int(self.names.shape[0])

    def select(self, keep: np.ndarray) -> FlatObjects:
        """The rows where keep (N,) is True, frame offsets recomputed."""
        frames = np.repeat(np.arange(self.offsets.shape[0] - 1), np.diff(self.offsets))
        per_frame = np.bincount(frames[keep], minlength=self.offsets.shape[0] - 1)
        return FlatObjects(
            names=self.names[keep],
            offsets=np.concatenate([[0], np.cumsum(per_frame)]).astype(np.int64),
            bbox=self.bbox[keep],
            alpha=self.alpha[keep],
            truncated=self.truncated[keep],
            occluded=self.occluded[keep],
            boxes=self.boxes[keep],
            has_3d=self.has_3d[keep],
            score=self.score[keep],
        )


def concatenate_objects(frames: Sequence[KittiObjects]) -> FlatObjects:
    """Per-frame rows -> one FlatObjects (scores 0 where a frame has none)."""
    counts = np.array([len(objects) for objects in frames], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    if counts.sum() == 0:
        return FlatObjects(
            names=np.zeros(0, dtype=str), offsets=offsets, bbox=np.zeros((0, 4)),
            alpha=np.zeros(0), truncated=np.zeros(0), occluded=np.zeros(0, dtype=np.int64),
            boxes=np.zeros((0, 7)), has_3d=np.zeros(0, dtype=bool), score=np.zeros(0),
        )  # fmt: skip
    present = [objects for objects in frames if len(objects)]

    def cat(field: str) -> np.ndarray:
        return np.concatenate([np.asarray(getattr(objects, field)) for objects in present])

    scores = [
        np.zeros(len(o)) if o.score is None else np.asarray(o.score, dtype=np.float64)
        for o in present
    ]
    joined = KittiObjects(
        names=cat("names"), truncated=cat("truncated").astype(np.float64),
        occluded=cat("occluded").astype(np.int64), alpha=cat("alpha").astype(np.float64),
        bbox=cat("bbox").astype(np.float64).reshape(-1, 4),
        dimensions=cat("dimensions").astype(np.float64).reshape(-1, 3),
        location=cat("location").astype(np.float64).reshape(-1, 3),
        rotation_y=cat("rotation_y").astype(np.float64), score=np.concatenate(scores),
    )  # fmt: skip
    return FlatObjects(
        names=np.char.lower(joined.names.astype(str)),
        offsets=offsets,
        bbox=joined.bbox,
        alpha=joined.alpha,
        truncated=joined.truncated,
        occluded=joined.occluded,
        boxes=upright_boxes_from_camera(joined.location, joined.dimensions, joined.rotation_y),
        has_3d=joined.has_3d,
        score=joined.score,
    )


def flatten_objects(
    gt: Sequence[KittiObjects], dt: Sequence[KittiObjects], gt_classes: set[str]
) -> tuple[FlatObjects, FlatObjects, FlatObjects]:
    """(ground truth of the lower-case `gt_classes`, DontCare regions, all detections).

    Ground truth of other classes can never be matched or missed, so it is dropped here.
    """
    gt_all = concatenate_objects(gt)
    relevant = np.isin(gt_all.names, sorted(gt_classes))
    dontcare = gt_all.select(gt_all.names == "dontcare")
    return gt_all.select(relevant), dontcare, concatenate_objects(dt)


def frame_overlaps(
    gt: FlatObjects, dt: FlatObjects, with_3d: bool = True
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Every frame's (num_dt, num_gt) overlap blocks, flattened row-major and concatenated.

    Returns ({"bbox": 2D IoU, "bev": BEV IoU, "3d": 3D IoU} each (P,), (F + 1,) offsets of the
    frame blocks). Pairs where either box lacks a 3D box have BEV / 3D IoU 0; with_3d=False
    leaves BEV / 3D all 0.
    """
    offsets, dt_index, gt_index = frame_pairs(dt.offsets, gt.offsets)
    a, b = dt.bbox[dt_index], gt.bbox[gt_index]
    iw = np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0])
    ih = np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1])
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    union = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]) + (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = union - inter
    iou_2d = np.where(inter > 0, inter / np.where(union > 0, union, 1.0), 0.0)

    iou_bev = np.zeros(offsets[-1])
    iou_3d = np.zeros(offsets[-1])
    if with_3d:
        pairs = np.flatnonzero(dt.has_3d[dt_index] & gt.has_3d[gt_index])
        box_dt, box_gt = dt.boxes[dt_index[pairs]], gt.boxes[gt_index[pairs]]
        iou_bev[pairs], iou_3d[pairs] = _rotated_ious(box_dt, box_gt)
    return {"bbox": iou_2d, "bev": iou_bev, "3d": iou_3d}, offsets


def frame_pairs(
    offsets_a: np.ndarray, offsets_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All same-frame row pairs of two frame-concatenated sets, frame by frame, row-major.

    offsets_a, offsets_b: (F + 1,) frame offsets. Returns ((F + 1,) offsets of each frame's
    (n_a, n_b) block, (P,) row of a, (P,) row of b).
    """
    num_a, num_b = np.diff(offsets_a), np.diff(offsets_b)
    sizes = num_a * num_b
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    frame = np.repeat(np.arange(sizes.shape[0]), sizes)
    local = np.arange(offsets[-1]) - offsets[frame]
    width = np.maximum(num_b[frame], 1)
    return offsets, offsets_a[frame] + local // width, offsets_b[frame] + local % width


def _rotated_ious(boxes1: np.ndarray, boxes2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 7), (K, 7) upright boxes -> ((K,) BEV IoU, (K,) 3D IoU), one BEV intersection each.

    Same formulas as geometry.paired_iou_bev / paired_iou_3d, sharing the polygon clipping.
    """
    bev = paired_bev_intersection(boxes1, boxes2)
    union_bev = boxes1[:, 3] * boxes1[:, 4] + boxes2[:, 3] * boxes2[:, 4] - bev
    top = np.minimum(boxes1[:, 2] + boxes1[:, 5] / 2, boxes2[:, 2] + boxes2[:, 5] / 2)
    bottom = np.maximum(boxes1[:, 2] - boxes1[:, 5] / 2, boxes2[:, 2] - boxes2[:, 5] / 2)
    volume = bev * np.clip(top - bottom, 0, None)
    union_3d = np.prod(boxes1[:, 3:6], axis=1) + np.prod(boxes2[:, 3:6], axis=1) - volume
    iou_bev = np.where(union_bev > 0, bev / np.where(union_bev > 0, union_bev, 1.0), 0.0)
    iou_3d = np.where(union_3d > 0, volume / np.where(union_3d > 0, union_3d, 1.0), 0.0)
    return np.clip(iou_bev, 0.0, 1.0), np.clip(iou_3d, 0.0, 1.0)
