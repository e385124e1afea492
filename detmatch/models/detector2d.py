"""CenterNet-style camera detector in plain PyTorch (the `Detector2D` contract).

forward(image) -> raw head maps; decode(maps) -> boxes, scores, classes, per-class
probabilities. Both take and return tensors only, so the export graph chains them. Boxes are in
the pixels of the network input; callers scale to the original image.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from detmatch.config import Detector2DConfig
from detmatch.constants import IMAGE_MEAN, IMAGE_STD
from detmatch.models.common import (
    HEATMAP_PRIOR_BIAS,
    draw_gaussian,
    gather_at,
    gaussian_radius,
    head,
    heatmap_focal_loss,
    heatmap_peaks,
    stage,
    tensor_like,
)
from detmatch.models.contract import Decoded, Detector2D
from detmatch.structures import LabeledBoxes


@dataclass(frozen=True)
class CenterNetTargets:
    """One image's targets on the stride-4 grid (h, w): heatmap (C, h, w) of Gaussian peaks;
    labelled_area (1, h, w) 1 where background is learned; per object the flat cell index
    (N,), size (N, 2) w, h in cells and the centre's sub-cell offset (N, 2)."""

    heatmap: np.ndarray
    labelled_area: np.ndarray
    index: np.ndarray
    size: np.ndarray
    offset: np.ndarray


class CenterNet2D(Detector2D):
    """Stride-4 CenterNet: heatmap (C), size (w, h in stride-4 cells) and sub-cell offset heads."""

    stride = 4
    output_names = ("heatmap", "size", "offset")

    def __init__(self, config: Detector2DConfig, num_classes: int) -> None:
        super().__init__()
        if len(config.widths) != 4 or len(config.depths) != 4:
            raise ValueError("detector2d.widths and .depths need 4 entries (strides 2, 4, 8, 16)")
        self.config = config
        self.num_classes = num_classes
        self.score_threshold = config.score_threshold
        widths = config.widths
        self.register_buffer("mean", torch.tensor(IMAGE_MEAN).view(1, 3, 1, 1) * 255.0)
        self.register_buffer("std", torch.tensor(IMAGE_STD).view(1, 3, 1, 1) * 255.0)
        self.stages = nn.ModuleList(
            stage(c_in, c_out, depth, stride=2)
            for c_in, c_out, depth in zip((3, *widths[:-1]), widths, config.depths, strict=True)
        )
        # Top-down path back to stride 4.
        self.lateral8 = nn.Conv2d(widths[2], widths[3], 1)
        self.lateral4 = nn.Conv2d(widths[1], widths[3], 1)
        self.smooth = nn.Sequential(
            nn.Conv2d(widths[3], config.head_width, 3, padding=1, bias=False),
            nn.BatchNorm2d(config.head_width),
            nn.ReLU(inplace=True),
        )
        self.heatmap_head = head(
            config.head_width, config.head_width, num_classes, HEATMAP_PRIOR_BIAS
        )
        self.size_head = head(config.head_width, config.head_width, 2)
        self.offset_head = head(config.head_width, config.head_width, 2)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """image: (B, 3, H, W) RGB in [0, 255], H and W multiples of 16.

        Returns heatmap logits (B, C, H/4, W/4), size (B, 2, H/4, W/4), offset (B, 2, H/4, W/4).
        """
        x = (image - self.mean) / self.std
        features = []
        for block in self.stages:
            x = block(x)
            features.append(x)
        top = features[3]
        top = F.interpolate(top, size=features[2].shape[-2:], mode="nearest") + self.lateral8(
            features[2]
        )
        top = F.interpolate(top, size=features[1].shape[-2:], mode="nearest") + self.lateral4(
            features[1]
        )
        shared = self.smooth(top)
        return self.heatmap_head(shared), self.size_head(shared), self.offset_head(shared)

    def decode(self, outputs: Sequence[torch.Tensor]) -> Decoded:
        """Head maps -> boxes (B, K, 4) xyxy input pixels, scores (B, K), classes (B, K),
        probabilities (B, K, C). Differentiable in the gathered values."""
        heatmap, size, offset = outputs
        width = heatmap.shape[3]
        scores, classes, pixel, probabilities = heatmap_peaks(
            torch.sigmoid(heatmap), self.config.max_detections
        )
        ys = torch.div(pixel, width, rounding_mode="floor")
        xs = pixel - ys * width
        box_size = gather_at(size, pixel).clamp(min=0.0)
        box_offset = gather_at(offset, pixel)
        centre_x = (xs.to(heatmap.dtype) + box_offset[..., 0]) * self.stride
        centre_y = (ys.to(heatmap.dtype) + box_offset[..., 1]) * self.stride
        half_w = box_size[..., 0] * self.stride / 2
        half_h = box_size[..., 1] * self.stride / 2
        boxes = torch.stack(
            [centre_x - half_w, centre_y - half_h, centre_x + half_w, centre_y + half_h], -1
        )
        return boxes, scores, classes, probabilities

    def build_targets(
        self,
        labels: LabeledBoxes,
        input_size: tuple[int, int],
        ignore: np.ndarray | None = None,
    ) -> CenterNetTargets:
        """Targets of one image from boxes in input pixels; input_size: (W, H). ignore: (M, 4)
        boxes in input pixels whose cells learn no background."""
        out_w, out_h = input_size[0] // self.stride, input_size[1] // self.stride
        heatmap = np.zeros((self.num_classes, out_h, out_w), dtype=np.float32)
        labelled_area = np.ones((out_h, out_w), dtype=bool)
        for box in np.zeros((0, 4)) if ignore is None else ignore:
            x1, y1 = np.clip(np.floor(box[:2] / self.stride), 0, (out_w, out_h)).astype(int)
            x2, y2 = np.clip(np.ceil(box[2:] / self.stride), 0, (out_w, out_h)).astype(int)
            labelled_area[y1:y2, x1:x2] = False
        index, box_size, box_offset = [], [], []
        for box, label in zip(labels.boxes, labels.classes, strict=True):
            w, h = (box[2] - box[0]) / self.stride, (box[3] - box[1]) / self.stride
            if w <= 0 or h <= 0:
                continue
            centre = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2]) / self.stride
            cell = np.floor(centre).astype(int)
            if not (0 <= cell[0] < out_w and 0 <= cell[1] < out_h):
                continue
            radius = max(0, int(gaussian_radius(math.ceil(h), math.ceil(w), 0.7)))
            draw_gaussian(heatmap[int(label)], cell[0], cell[1], radius)
            index.append(cell[1] * out_w + cell[0])
            box_size.append((w, h))
            box_offset.append(centre - cell)
        return CenterNetTargets(
            heatmap=heatmap,
            labelled_area=labelled_area[None].astype(np.float32),
            index=np.asarray(index, dtype=np.int64),
            size=np.asarray(box_size, dtype=np.float32).reshape(-1, 2),
            offset=np.asarray(box_offset, dtype=np.float32).reshape(-1, 2),
        )

    def loss(
        self,
        outputs: Sequence[torch.Tensor],
        targets: Sequence[CenterNetTargets],
        box_regression: bool = True,
    ) -> dict[str, torch.Tensor]:
        """Losses against per-image targets from build_targets. Without box_regression only the
        classification (heatmap) loss is returned: the pseudo-label loss of docs/design.md
        section 3."""
        heatmap, size, offset = outputs
        target_heatmap = tensor_like(np.stack([t.heatmap for t in targets]), heatmap)
        area = tensor_like(np.stack([t.labelled_area for t in targets]), heatmap)
        focal = heatmap_focal_loss(heatmap, target_heatmap, area)
        losses = {"heatmap": self.config.heatmap_weight * focal}
        if box_regression:
            losses.update(regression_losses(size, offset, targets, self.config))
        return losses


def regression_losses(
    size: torch.Tensor,
    offset: torch.Tensor,
    targets: Sequence[CenterNetTargets],
    config: Detector2DConfig,
) -> dict[str, torch.Tensor]:
    """L1 on size and offset at the object centres, averaged over objects."""
    size_terms, offset_terms = [], []
    for b, target in enumerate(targets):
        if len(target.index) == 0:
            continue
        index = tensor_like(target.index, size)
        predicted_size = size[b].flatten(1)[:, index].t()
        predicted_offset = offset[b].flatten(1)[:, index].t()
        size_terms.append(
            F.l1_loss(predicted_size, tensor_like(target.size, size), reduction="sum")
        )
        offset_terms.append(
            F.l1_loss(predicted_offset, tensor_like(target.offset, size), reduction="sum")
        )
    count = max(sum(len(t.index) for t in targets), 1)
    zero = size.sum() * 0.0
    return {
        "size": config.size_weight * (sum(size_terms, zero) / count),
        "offset": config.offset_weight * (sum(offset_terms, zero) / count),
    }
