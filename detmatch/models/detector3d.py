"""PointPillars encoder + CenterPoint-style head in plain PyTorch (the `Detector3D` contract).

Pillars come from `detmatch.models.pillars.pillarize` (numpy, shared with serving). forward
takes pillar tensors and returns raw head maps; decode turns maps into LiDAR-frame boxes with
per-class probabilities. Single stage: the consistency loss's box gradient goes into the dense
box regression.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from detmatch.config import Detector3DConfig
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
from detmatch.models.contract import ConsistencyCandidates, Decoded, Detector3D, LabelledArea
from detmatch.models.pillars import PILLAR_FEATURES, PillarGrid
from detmatch.models.refine import BoxRefinement, nearest_labels, residual_targets
from detmatch.structures import LabeledBoxes

# Regression channels: x, y offsets in the cell, z, log l, log w, log h, sin yaw, cos yaw.
REGRESSION_CHANNELS = 8


def pillar_grid(config: Detector3DConfig) -> PillarGrid:
    return PillarGrid(
        config.point_cloud_range,
        config.pillar_size,
        config.max_points_per_pillar,
        config.max_pillars,
    )


class PillarFeatureNet(nn.Module):
    """Linear + BN + ReLU on each point slot of the padded (P, M) layout, max over the pillar's
    points. BatchNorm's batch statistics include the zero padding slots (OpenPCDet's PFN does
    the same).

    Training computes the same function on the real points only (`_forward_points`): the
    padding slots' contribution to the statistics is added in closed form and the max is a
    segment max over the points, which skips the padding (most of the slots: about 6x fewer
    rows on the synthetic set). Inference and the exported graph run the padded layout
    (`_forward_padded`), whose ops export to ONNX opset 17.
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.linear = nn.Linear(PILLAR_FEATURES, channels, bias=False)
        self.norm = nn.BatchNorm1d(channels)

    def forward(self, features: torch.Tensor, num_points: torch.Tensor) -> torch.Tensor:
        """features (P, M, 9), num_points (P,) -> (P, channels)."""
        if self.training and not torch.jit.is_tracing():
            return self._forward_points(features, num_points)
        return self._forward_padded(features, num_points)

    def _valid(self, features: torch.Tensor, num_points: torch.Tensor) -> torch.Tensor:
        """(P, M) bool: the slots that hold a point."""
        slots = torch.arange(features.shape[1], device=features.device)
        return slots.unsqueeze(0) < num_points.unsqueeze(1)

    def _forward_padded(self, features: torch.Tensor, num_points: torch.Tensor) -> torch.Tensor:
        pillars, max_points, _ = features.shape
        x = self.linear(features.reshape(pillars * max_points, PILLAR_FEATURES))
        x = F.relu(self.norm(x)).reshape(pillars, max_points, self.linear.out_features)
        valid = self._valid(features, num_points)
        return (x * valid.unsqueeze(-1).to(x.dtype)).amax(dim=1)

    def _forward_points(self, features: torch.Tensor, num_points: torch.Tensor) -> torch.Tensor:
        """Training-mode BatchNorm over all P * M slots, computed from the real points: a
        padding slot's linear output is exactly 0 (no bias), so it adds 0 to the sum and
        mean^2 to the squared deviations; its ReLU output is masked to 0, which the max over a
        ReLU (>= 0) already allows for."""
        pillars, max_points, _ = features.shape
        valid = self._valid(features, num_points)
        rows = pillars * max_points
        x = self.linear(features[valid])  # (N, C), the real points
        mean = x.sum(dim=0) / rows
        padding = rows - x.shape[0]
        var = (((x - mean) ** 2).sum(dim=0) + padding * mean**2) / rows
        norm = self.norm
        if norm.track_running_stats:
            with torch.no_grad():
                momentum = norm.momentum if norm.momentum is not None else 0.1
                unbiased = var * rows / max(rows - 1, 1)
                norm.running_mean.mul_(1 - momentum).add_(momentum * mean)
                norm.running_var.mul_(1 - momentum).add_(momentum * unbiased)
                norm.num_batches_tracked.add_(1)
        x = (x - mean) * torch.rsqrt(var + norm.eps) * norm.weight + norm.bias
        # features[valid] lists each pillar's points in turn: a segment max over the counts.
        return torch.segment_reduce(F.relu(x), "max", lengths=num_points, axis=0, unsafe=True)


@dataclass(frozen=True)
class CenterPointTargets:
    """One frame's targets on the output grid (h, w): heatmap (C, h, w) of Gaussian peaks;
    labelled_area (1, h, w) 1 where background is learned; per object the flat cell index
    (N,) and regression (N, 8): x, y offsets in the cell, z, log l, log w, log h, sin, cos yaw;
    boxes (N, 7) the labels themselves (the second stage's targets)."""

    heatmap: np.ndarray
    labelled_area: np.ndarray
    index: np.ndarray
    regression: np.ndarray
    boxes: np.ndarray


class PointPillars3D(Detector3D):
    """Pillar encoder -> BEV pseudo-image -> multi-scale backbone -> CenterPoint heads, and with
    [detector3d] refine a light second stage (detmatch.models.refine)."""

    def __init__(self, config: Detector3DConfig, num_classes: int) -> None:
        super().__init__()
        if len(config.widths) != len(config.depths):
            raise ValueError("detector3d.widths and .depths must have the same length")
        self.config = config
        self.num_classes = num_classes
        self.score_threshold = config.score_threshold
        self.grid = pillar_grid(config)
        ny, nx = self.grid.shape
        total_stride = 2 ** len(config.widths)
        if ny % total_stride or nx % total_stride:
            raise ValueError(
                f"the pillar grid {ny}x{nx} must divide by the backbone's stride {total_stride}"
            )
        if config.out_stride not in (2**i for i in range(1, len(config.widths) + 1)):
            raise ValueError(
                f"out_stride must be one of the backbone strides, got {config.out_stride}"
            )
        self.encoder = PillarFeatureNet(config.pillar_channels)
        self.stages = nn.ModuleList(
            stage(c_in, c_out, depth, stride=2)
            for c_in, c_out, depth in zip(
                (config.pillar_channels, *config.widths[:-1]),
                config.widths,
                config.depths,
                strict=True,
            )
        )
        self.merge = nn.ModuleList(
            nn.Conv2d(width, config.head_width, 1) for width in config.widths
        )
        self.neck = nn.Sequential(
            nn.Conv2d(config.head_width, config.head_width, 3, padding=1, bias=False),
            nn.BatchNorm2d(config.head_width),
            nn.ReLU(inplace=True),
        )
        self.heatmap_head = head(
            config.head_width, config.head_width, num_classes, HEATMAP_PRIOR_BIAS
        )
        self.regression_head = head(config.head_width, config.head_width, REGRESSION_CHANNELS)
        self.output_names = ("heatmap", "regression")
        self.consistency_gradient = "the dense head's box regression (single-stage detector)"
        self.refinement = None
        if config.refine:
            origin = (config.point_cloud_range[0], config.point_cloud_range[1])
            self.refinement = BoxRefinement(config.head_width, origin, self.cell_size)
            self.output_names = ("heatmap", "regression", "bev_features")
            self.consistency_gradient = "the second stage's box refinement only"

    @property
    def output_shape(self) -> tuple[int, int]:
        ny, nx = self.grid.shape
        return ny // self.config.out_stride, nx // self.config.out_stride

    @property
    def cell_size(self) -> tuple[float, float]:
        """(dx, dy) metres of one output cell."""
        return (
            self.config.pillar_size[0] * self.config.out_stride,
            self.config.pillar_size[1] * self.config.out_stride,
        )

    def forward(
        self,
        features: torch.Tensor,
        coords: torch.Tensor,
        counts: torch.Tensor,
        batch_size: int = 1,
    ) -> tuple[torch.Tensor, ...]:
        """features (P, M, 9), coords (P, 3) int64 (batch, iy, ix), counts (P,).

        Returns heatmap logits (B, C, h, w) and regression (B, 8, h, w) on the output grid, and
        with refine the shared BEV features (B, head_width, h, w) the second stage samples.
        """
        ny, nx = self.grid.shape
        encoded = self.encoder(features, counts)
        flat = coords[:, 0] * (ny * nx) + coords[:, 1] * nx + coords[:, 2]
        canvas = encoded.new_zeros(batch_size * ny * nx, encoded.shape[1])
        canvas = canvas.index_put((flat,), encoded)
        x = canvas.reshape(batch_size, ny, nx, -1).permute(0, 3, 1, 2)
        out_h, out_w = self.output_shape
        merged = None
        for block, merge in zip(self.stages, self.merge, strict=True):
            x = block(x)
            lifted = merge(x)
            if lifted.shape[-2:] != (out_h, out_w):
                if lifted.shape[-2] < out_h:
                    lifted = F.interpolate(lifted, size=(out_h, out_w), mode="nearest")
                else:
                    lifted = F.adaptive_avg_pool2d(lifted, (out_h, out_w))
            merged = lifted if merged is None else merged + lifted
        shared = self.neck(merged)
        maps = (self.heatmap_head(shared), self.regression_head(shared))
        return (*maps, shared) if self.refinement is not None else maps

    def decode(self, outputs: Sequence[torch.Tensor]) -> Decoded:
        """Head maps -> boxes (B, K, 7) LiDAR x y z l w h yaw, scores (B, K), classes (B, K),
        probabilities (B, K, C). Differentiable in the gathered values."""
        heatmap, regression = outputs[:2]
        scores, classes, _, probabilities, boxes = self._peaks(torch.sigmoid(heatmap), regression)
        if self.refinement is not None:
            boxes = self.refinement(outputs[2], boxes)
        return boxes, scores, classes, probabilities

    def consistency_candidates(self, outputs: Sequence[torch.Tensor]) -> ConsistencyCandidates:
        """The top-k peaks of the detached heatmap with their class logits (which keep their
        gradients) and boxes: decoded from the dense regression (its gradient kept), or with
        refine the second stage's refinement of the detached dense boxes (only the refinement
        keeps a gradient)."""
        heatmap, regression = outputs[:2]
        scores, _, pixel, probabilities, boxes = self._peaks(
            torch.sigmoid(heatmap).detach(), regression
        )
        if self.refinement is not None:
            boxes = self.refinement(outputs[2], boxes)
        return ConsistencyCandidates(boxes, gather_at(heatmap, pixel), scores, probabilities)

    def _peaks(
        self, heatmap_probabilities: torch.Tensor, regression: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        """The top-k peaks of heatmap probabilities (B, C, h, w): scores, classes, pixels,
        probabilities, and the dense head's boxes (B, K, 7) decoded at them."""
        scores, classes, pixel, probabilities = heatmap_peaks(
            heatmap_probabilities, self.config.max_detections
        )
        width = heatmap_probabilities.shape[3]
        boxes = self.boxes_from_regression(pixel, gather_at(regression, pixel), width)
        return scores, classes, pixel, probabilities, boxes

    def boxes_from_regression(
        self, pixel: torch.Tensor, values: torch.Tensor, width: int
    ) -> torch.Tensor:
        """Flat output-cell indices (B, K) and regression values (B, K, 8) -> (B, K, 7) boxes."""
        x_min, y_min = self.config.point_cloud_range[0], self.config.point_cloud_range[1]
        cell_x, cell_y = self.cell_size
        ys = torch.div(pixel, width, rounding_mode="floor")
        xs = pixel - ys * width
        centre_x = (xs.to(values.dtype) + values[..., 0]) * cell_x + x_min
        centre_y = (ys.to(values.dtype) + values[..., 1]) * cell_y + y_min
        dims = torch.exp(values[..., 3:6].clamp(max=4.0))
        yaw = torch.atan2(values[..., 6], values[..., 7])
        return torch.cat(
            [centre_x[..., None], centre_y[..., None], values[..., 2:3], dims, yaw[..., None]], -1
        )

    def cell_centres(self) -> np.ndarray:
        """(h, w, 2) x, y metres of the output cells' centres, LiDAR frame."""
        out_h, out_w = self.output_shape
        cell_x, cell_y = self.cell_size
        x_min, y_min = self.config.point_cloud_range[0], self.config.point_cloud_range[1]
        xs = (np.arange(out_w) + 0.5) * cell_x + x_min
        ys = (np.arange(out_h) + 0.5) * cell_y + y_min
        return np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)

    def _centre_cell(self, box: np.ndarray) -> tuple[np.ndarray, np.ndarray, int] | None:
        """A box's centre in output cells, its cell and its Gaussian radius in cells (None:
        outside the grid or degenerate)."""
        out_h, out_w = self.output_shape
        cell_x, cell_y = self.cell_size
        x_min, y_min = self.config.point_cloud_range[0], self.config.point_cloud_range[1]
        centre = np.array([(box[0] - x_min) / cell_x, (box[1] - y_min) / cell_y])
        cell = np.floor(centre).astype(int)
        if not (0 <= cell[0] < out_w and 0 <= cell[1] < out_h) or np.any(box[3:6] <= 0):
            return None
        return centre, cell, max(2, int(gaussian_radius(box[3] / cell_x, box[4] / cell_y, 0.1)))

    def build_targets(
        self,
        labels: LabeledBoxes,
        view: LabelledArea | None = None,
        ignore: np.ndarray | None = None,
    ) -> CenterPointTargets:
        """Targets of one frame from LiDAR boxes in the input frame. view: background is
        learned only in output cells inside the camera's view (KITTI labels only that), or
        everywhere when None. ignore: (M, 7) boxes whose surroundings (the square a label's
        Gaussian would span) learn no background."""
        out_h, out_w = self.output_shape
        heatmap = np.zeros((self.num_classes, out_h, out_w), dtype=np.float32)
        labelled_area = np.ones((out_h, out_w), dtype=bool)
        if view is not None:
            centres = self.cell_centres()
            labelled_area = view.contains_bev(centres.reshape(-1, 2)).reshape(out_h, out_w)
        for box in np.zeros((0, 7)) if ignore is None else ignore:
            if (found := self._centre_cell(box)) is not None:
                (x, y), r = found[1], found[2]
                labelled_area[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1] = False
        index, regression = [], []
        for box, label in zip(labels.boxes, labels.classes, strict=True):
            if (found := self._centre_cell(box)) is None:
                continue
            centre, cell, radius = found
            draw_gaussian(heatmap[int(label)], cell[0], cell[1], radius)
            index.append(cell[1] * out_w + cell[0])
            regression.append(
                [*(centre - cell), box[2], *np.log(box[3:6]), math.sin(box[6]), math.cos(box[6])]
            )
        return CenterPointTargets(
            heatmap=heatmap,
            labelled_area=labelled_area[None].astype(np.float32),
            index=np.asarray(index, dtype=np.int64),
            regression=np.asarray(regression, dtype=np.float32).reshape(-1, REGRESSION_CHANNELS),
            boxes=np.asarray(labels.boxes, dtype=np.float64).reshape(-1, 7),
        )

    def loss(
        self,
        outputs: Sequence[torch.Tensor],
        targets: Sequence[CenterPointTargets],
        box_regression: bool = True,
    ) -> dict[str, torch.Tensor]:
        """Focal heatmap loss and L1 regression at object centres (averaged over objects)."""
        heatmap, regression = outputs[:2]
        target_heatmap = tensor_like(np.stack([t.heatmap for t in targets]), heatmap)
        area = tensor_like(np.stack([t.labelled_area for t in targets]), heatmap)
        focal = heatmap_focal_loss(heatmap, target_heatmap, area)
        losses = {"heatmap": self.config.heatmap_weight * focal}
        if box_regression:
            terms = []
            for b, target in enumerate(targets):
                if len(target.index):
                    index = tensor_like(target.index, regression)
                    predicted = regression[b].flatten(1)[:, index].t()
                    terms.append(
                        F.l1_loss(
                            predicted,
                            tensor_like(target.regression, regression),
                            reduction="sum",
                        )
                    )
            count = max(sum(len(t.index) for t in targets), 1)
            total = sum(terms, regression.sum() * 0.0) / count
            losses["regression"] = self.config.regression_weight * total
            if self.refinement is not None:
                losses["refine"] = self.config.refine_weight * self.refine_loss(outputs, targets)
        return losses

    def refine_loss(
        self, outputs: Sequence[torch.Tensor], targets: Sequence[CenterPointTargets]
    ) -> torch.Tensor:
        """Smooth L1 of the second stage's residuals, for the detached top-k boxes whose
        nearest labeled box is close (detmatch.models.refine.nearest_labels), averaged over
        them."""
        heatmap, regression, features = outputs
        with torch.no_grad():
            rois = self._peaks(torch.sigmoid(heatmap), regression)[4]
        residual = self.refinement.residual(features, rois)
        terms = []
        for b, target in enumerate(targets):
            frame_rois = rois[b].detach().cpu().double().numpy()
            rows = nearest_labels(frame_rois, target.boxes)
            chosen = np.flatnonzero(rows >= 0)
            if len(chosen):
                wanted = residual_targets(frame_rois[chosen], target.boxes[rows[chosen]])
                index = tensor_like(chosen, residual)
                terms.append(
                    F.smooth_l1_loss(residual[b][index], tensor_like(wanted, residual),
                                     beta=1 / 9, reduction="none").sum(dim=1)
                )  # fmt: skip
        if not terms:
            return residual.sum() * 0.0
        return torch.cat(terms).mean()
