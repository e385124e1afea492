"""The 2D-teacher -> 3D-student consistency loss of DetMatch (docs/design.md section 3).

The 3D student's predictions on an unlabeled frame are decoded differentiably, moved back to
the un-augmented frame, projected into the image, matched to the 2D teacher's matched
pseudo-labels with the same Hungarian cost, and pulled towards them:
2 * focal(class logits, teacher class) + 20 * L1(normalised xyxy) + 2 * (1 - GIoU).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from detmatch.data.augment import CloudTransform
from detmatch.data.dataset import Sample
from detmatch.geometry import (
    CONSISTENCY_MIN_CORNERS,
    CONSISTENCY_MIN_MEAN_DEPTH,
    PROJECTION_MIN_DEPTH,
    greedy_nms,
    pairwise_iou_2d,
    pairwise_iou_bev,
)
from detmatch.matching import hungarian_match, matching_cost
from detmatch.models.common import sigmoid_focal_loss
from detmatch.models.contract import Detector3D
from detmatch.structures import Calibration, LabeledBoxes

_UNIT = 0.5 * torch.tensor(
    [[1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, -1],
     [1, -1, 1], [1, 1, 1], [-1, 1, 1], [-1, -1, 1]],
    dtype=torch.float32,
)  # fmt: skip


def box_corners_torch(boxes: torch.Tensor) -> torch.Tensor:
    """(N, 7) LiDAR boxes -> (N, 8, 3) corners, same order as detmatch.geometry.box3d_corners."""
    local = _UNIT.to(boxes)[None] * boxes[:, None, 3:6]
    c, s = torch.cos(boxes[:, 6])[:, None], torch.sin(boxes[:, 6])[:, None]
    x = local[..., 0] * c - local[..., 1] * s
    y = local[..., 0] * s + local[..., 1] * c
    return torch.stack([x, y, local[..., 2]], dim=-1) + boxes[:, None, 0:3]


def project_boxes_torch(
    boxes: torch.Tensor, calib: Calibration, image_size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable docs/design.md step-1 projection of (N, 7) LiDAR boxes.

    Returns (N, 4) clipped xyxy boxes and (N,) bool validity, the torch twin of
    `detmatch.geometry.boxes_usable_for_consistency`.
    """
    width, height = image_size
    corners = box_corners_torch(boxes)
    projection = torch.as_tensor(calib.lidar_to_image, dtype=boxes.dtype, device=boxes.device)
    homogeneous = torch.cat([corners, torch.ones_like(corners[..., :1])], dim=-1)
    projected = homogeneous @ projection.T
    depth = projected[..., 2]
    uv = projected[..., :2] / depth.clamp(min=PROJECTION_MIN_DEPTH)[..., None]
    inside = (
        (depth > 0)
        & (uv[..., 0] >= 0)
        & (uv[..., 0] < width)
        & (uv[..., 1] >= 0)
        & (uv[..., 1] < height)
    )
    valid = (inside.sum(dim=1) >= CONSISTENCY_MIN_CORNERS) & (
        depth.mean(dim=1) >= CONSISTENCY_MIN_MEAN_DEPTH
    )
    low = uv.min(dim=1).values
    high = uv.max(dim=1).values
    xyxy = torch.stack(
        [low[:, 0].clamp(0, width - 1), low[:, 1].clamp(0, height - 1),
         high[:, 0].clamp(0, width - 1), high[:, 1].clamp(0, height - 1)], dim=1,
    )  # fmt: skip
    return xyxy, valid


def giou_torch(boxes1: torch.Tensor, boxes2: torch.Tensor) -> torch.Tensor:
    """Row-wise generalised IoU of (N, 4) xyxy boxes."""
    area1 = (boxes1[:, 2] - boxes1[:, 0]).clamp(min=0) * (boxes1[:, 3] - boxes1[:, 1]).clamp(min=0)
    area2 = (boxes2[:, 2] - boxes2[:, 0]).clamp(min=0) * (boxes2[:, 3] - boxes2[:, 1]).clamp(min=0)
    low = torch.maximum(boxes1[:, :2], boxes2[:, :2])
    high = torch.minimum(boxes1[:, 2:], boxes2[:, 2:])
    inter = (high - low).clamp(min=0).prod(dim=1)
    union = area1 + area2 - inter
    hull = (
        (torch.maximum(boxes1[:, 2:], boxes2[:, 2:]) - torch.minimum(boxes1[:, :2], boxes2[:, :2]))
        .clamp(min=0)
        .prod(dim=1)
    )
    eps = 1e-7
    return inter / (union + eps) - (hull - union) / (hull + eps)


# The authors' candidate filter (docs/design.md section 3): BEV NMS, then 2D NMS on projections.
CANDIDATE_BEV_NMS = 0.1
CANDIDATE_IMAGE_NMS = 0.5


@dataclass(frozen=True)
class ConsistencyWeights:
    """The loss's weights and switches ([ssl] consistency_*); reduction "pairs" or "frames",
    nms: the authors' candidate filter."""

    class_weight: float = 2.0
    l1_weight: float = 20.0
    giou_weight: float = 2.0
    use_class: bool = True
    use_box: bool = True
    reduction: str = "pairs"
    nms: bool = False


def candidate_nms(boxes: np.ndarray, projected: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Rows of a frame's candidates that survive BEV NMS (IoU 0.1) and then 2D NMS (0.5) on
    their projections, best score first."""
    rows = greedy_nms(pairwise_iou_bev(boxes, boxes), scores, CANDIDATE_BEV_NMS)
    iou_2d = pairwise_iou_2d(projected[rows], projected[rows])
    return rows[greedy_nms(iou_2d, scores[rows], CANDIDATE_IMAGE_NMS)]


def consistency_loss(
    model_3d: Detector3D,
    outputs: Sequence[torch.Tensor],
    samples: Sequence[Sample],
    clouds: Sequence[CloudTransform],
    targets: Sequence[LabeledBoxes],
    weights: ConsistencyWeights,
    tau_hung: float,
) -> tuple[torch.Tensor, int]:
    """Consistency loss over a batch of the 3D student's raw outputs on the strong views.

    samples: the frames' weak samples (calibration, original image size); clouds: un-augmented
    -> student frame; targets: each frame's matched 2D teacher boxes (original pixels) with
    their probabilities. The student's candidates come from the detector's
    `consistency_candidates`. Returns the loss (mean over matched pairs, 0 when none) and the
    number of matched pairs.
    """
    candidates = model_3d.consistency_candidates(outputs)
    class_terms, l1_terms, giou_terms = [], [], []
    pairs = 0
    for b, target in enumerate(targets):
        keep = candidates.scores[b] > model_3d.score_threshold
        if len(target) == 0 or not bool(keep.any()):
            continue
        calib, image_size = samples[b].calib, samples[b].image_transform.original_size
        unaugmented = clouds[b].invert_boxes_torch(candidates.boxes[b][keep])
        projected, valid = project_boxes_torch(unaugmented, calib, image_size)
        if not bool(valid.any()):
            continue
        projected, frame_logits = projected[valid], candidates.logits[b][keep][valid]
        frame_probabilities = candidates.probabilities[b][keep][valid]
        if weights.nms:
            rows = candidate_nms(
                unaugmented[valid].detach().cpu().double().numpy(),
                projected.detach().cpu().double().numpy(),
                candidates.scores[b][keep][valid].cpu().double().numpy(),
            )
            rows_t = torch.from_numpy(rows).to(projected.device)
            projected, frame_logits = projected[rows_t], frame_logits[rows_t]
            frame_probabilities = frame_probabilities[rows_t]
        cost = matching_cost(
            projected.detach().cpu().double().numpy(),
            frame_probabilities.cpu().double().numpy(),
            target.boxes,
            target.probabilities,
            image_size,
        )
        rows, cols = hungarian_match(cost, tau_hung)
        if rows.size == 0:
            continue
        rows_t = torch.from_numpy(rows).to(projected.device)
        cols_t = torch.from_numpy(cols).to(projected.device)
        pairs += len(rows)
        if weights.use_class:
            onehot = torch.zeros_like(frame_logits[rows_t])
            classes = rows_t.new_tensor(target.classes[cols])
            onehot[torch.arange(len(rows), device=rows_t.device), classes] = 1.0
            focal = sigmoid_focal_loss(frame_logits[rows_t], onehot)
            per_pair = focal.mean(dim=1) if weights.reduction == "frames" else focal.sum(dim=1)
            class_terms.append(per_pair)
        if weights.use_box:
            w, h = image_size
            scale = projected.new_tensor([w, h, w, h])
            teacher = projected.new_tensor(target.boxes)[cols_t]
            l1_terms.append((projected[rows_t] / scale - teacher / scale).abs().mean(dim=1))
            giou_terms.append(1.0 - giou_torch(projected[rows_t], teacher))
    loss = outputs[0].sum() * 0.0
    for weight, terms in (
        (weights.class_weight, class_terms),
        (weights.l1_weight, l1_terms),
        (weights.giou_weight, giou_terms),
    ):
        if terms:
            loss = loss + weight * _reduce(terms, weights.reduction)
    return loss, pairs


def _reduce(terms: list[torch.Tensor], reduction: str) -> torch.Tensor:
    """Per-frame pair terms -> one value: the mean over every pair ("pairs"), or the mean of
    each frame's mean ("frames"; only frames with matches have terms)."""
    if reduction == "frames":
        return torch.stack([t.mean() for t in terms]).mean()
    return torch.cat(terms).mean()
