"""The 2D-teacher -> 3D-student consistency loss of DetMatch (docs/design.md section 3).

The 3D student's predictions on an unlabeled frame are decoded differentiably, moved back to
the un-augmented frame, projected into the image, matched to the 2D teacher's matched
pseudo-labels with the same Hungarian cost, and pulled towards them:
2 * focal(class logits, teacher class) + 20 * L1(normalised xyxy) + 2 * (1 - GIoU).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from detmatch.constants import (
    CONSISTENCY_CLASS_WEIGHT,
    CONSISTENCY_GIOU_WEIGHT,
    CONSISTENCY_L1_WEIGHT,
)
from detmatch.data.augment import CloudTransform
from detmatch.data.dataset import Sample
from detmatch.geometry import (
    CONSISTENCY_MIN_CORNERS,
    CONSISTENCY_MIN_MEAN_DEPTH,
    PROJECTION_MIN_DEPTH,
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


@dataclass(frozen=True)
class ConsistencyWeights:
    """The loss's weights and switches ([ssl] consistency_*)."""

    class_weight: float = CONSISTENCY_CLASS_WEIGHT
    l1_weight: float = CONSISTENCY_L1_WEIGHT
    giou_weight: float = CONSISTENCY_GIOU_WEIGHT
    use_class: bool = True
    use_box: bool = True


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
            class_terms.append(sigmoid_focal_loss(frame_logits[rows_t], onehot).sum(dim=1))
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
        if terms:  # every matched pair of the batch alike; focal summed over classes
            loss = loss + weight * torch.cat(terms).mean()
    return loss, pairs
