"""2D-3D Hungarian matching of teacher detections (docs/design.md section 3), numpy + scipy only.

Training and the labeling service both use this module, so it must never import torch.
Cost of pairing 3D box i (projected to the image) with 2D box j:

    C = C_cls + C_L1 + C_iou
    C_cls = f(s3_i[c2_j]) + f(s2_j[c3_i])         double-sided focal term
    C_L1  = 5 * sum_k |b_ik - b_jk| / S_k         xyxy, S = (W, H, W, H)
    C_iou = -2 * GIoU(b_i, b_j)

with f(p) = 0.25 (1 - p)^2 (-log(p + 1e-12)) - 0.75 p^2 (-log(1 - p + 1e-12)), p clamped to
[1e-6, 1 - 1e-6]. Good matches cost less than zero: identical boxes with both probabilities
0.9 on the same class cost about -4.8. Pairs are kept when their assigned cost <= tau_hung.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from detmatch.constants import TAU_HUNG
from detmatch.geometry import pairwise_giou_2d

FOCAL_ALPHA = 0.25
FOCAL_GAMMA = 2.0
L1_WEIGHT = 5.0
GIOU_WEIGHT = 2.0
# The classification cost is weighted 2 and then halved over its two sides: net weight 1.
CLASS_WEIGHT = 1.0


def focal_cost(probability: np.ndarray) -> np.ndarray:
    """Elementwise focal matching cost f(p): negative for confident p, positive for low p."""
    p = np.clip(np.asarray(probability, dtype=np.float64), 1e-6, 1 - 1e-6)
    positive = FOCAL_ALPHA * (1 - p) ** FOCAL_GAMMA * (-np.log(p + 1e-12))
    negative = (1 - FOCAL_ALPHA) * p**FOCAL_GAMMA * (-np.log(1 - p + 1e-12))
    return positive - negative


def classification_cost(probs_3d: np.ndarray, probs_2d: np.ndarray) -> np.ndarray:
    """(N3, C), (N2, C) class probabilities -> (N3, N2) double-sided focal cost:
    f(s3_i[argmax s2_j]) + f(s2_j[argmax s3_i])."""
    probs_3d = np.asarray(probs_3d, dtype=np.float64)
    probs_2d = np.asarray(probs_2d, dtype=np.float64)
    if probs_3d.ndim != 2 or probs_2d.ndim != 2:
        raise ValueError(f"probabilities must be (N, C), got {probs_3d.shape} and {probs_2d.shape}")
    if probs_3d.shape[1] != probs_2d.shape[1]:
        raise ValueError(
            f"probs_3d has {probs_3d.shape[1]} classes, probs_2d has {probs_2d.shape[1]}"
        )
    class_3d = probs_3d.argmax(axis=1) if len(probs_3d) else np.zeros(0, dtype=int)
    class_2d = probs_2d.argmax(axis=1) if len(probs_2d) else np.zeros(0, dtype=int)
    three_d_on_2d_class = probs_3d[:, class_2d]  # (N3, N2): s3_i[c2_j]
    two_d_on_3d_class = probs_2d[:, class_3d].T  # (N3, N2): s2_j[c3_i]
    return CLASS_WEIGHT * (focal_cost(three_d_on_2d_class) + focal_cost(two_d_on_3d_class))


def l1_cost(
    boxes_proj: np.ndarray, boxes_2d: np.ndarray, image_size: tuple[int, int]
) -> np.ndarray:
    """(N3, 4), (N2, 4) xyxy pixels -> (N3, N2) 5 * L1 distance of image-normalised boxes."""
    width, height = image_size
    scale = np.array([width, height, width, height], dtype=np.float64)
    a = np.asarray(boxes_proj, dtype=np.float64).reshape(-1, 4) / scale
    b = np.asarray(boxes_2d, dtype=np.float64).reshape(-1, 4) / scale
    return L1_WEIGHT * np.abs(a[:, None, :] - b[None, :, :]).sum(axis=-1)


def matching_cost(
    boxes_proj: np.ndarray,
    probs_3d: np.ndarray,
    boxes_2d: np.ndarray,
    probs_2d: np.ndarray,
    image_size: tuple[int, int],
) -> np.ndarray:
    """The (N3, N2) matching cost C = C_cls + C_L1 + C_iou.

    boxes_proj: (N3, 4) 3D teacher boxes projected to the un-augmented image (xyxy pixels);
    probs_3d: (N3, C); boxes_2d: (N2, 4) 2D teacher boxes, same image; probs_2d: (N2, C);
    image_size: (W, H) of that image.
    """
    boxes_proj = np.asarray(boxes_proj, dtype=np.float64).reshape(-1, 4)
    boxes_2d = np.asarray(boxes_2d, dtype=np.float64).reshape(-1, 4)
    if len(probs_3d) != len(boxes_proj) or len(probs_2d) != len(boxes_2d):
        raise ValueError("each box needs one probability vector")
    cost_iou = -GIOU_WEIGHT * pairwise_giou_2d(boxes_proj, boxes_2d)
    return (
        classification_cost(probs_3d, probs_2d)
        + l1_cost(boxes_proj, boxes_2d, image_size)
        + cost_iou
    )


def hungarian_match(cost: np.ndarray, threshold: float = TAU_HUNG) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-cost one-to-one assignment of a (N3, N2) cost matrix; returns the (rows, cols)
    of assigned pairs whose cost is <= threshold, rows ascending."""
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2:
        raise ValueError(f"cost must be a matrix, got shape {cost.shape}")
    if cost.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if not np.all(np.isfinite(cost)):
        raise ValueError("cost holds NaN or Inf")
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] <= threshold
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)
