"""A light second stage for a bird's-eye-view 3D detector (CenterPoint's two-stage refinement,
much reduced): each first-stage box, detached, samples the detached BEV feature map at its
centre and the midpoints of its four sides; an MLP predicts a residual that refines the box.

It exists so that the 2D-teacher -> 3D-student consistency loss has a box regressor of its own
to pull on, as the authors' PV-RCNN has (its RoI head): the consistency gradient reaches the
refinement only, never the dense head's box regression that the labels train. The refinement
itself is trained on labeled frames (and pseudo-labels) by the residual to the nearest labeled
box. Everything here is traceable, so refined boxes are what the exported graph outputs.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from detmatch.geometry import nearest_in_bev

# Residual channels: dx, dy (box frame, over the box's BEV diagonal), dz (over h), log l, log w,
# log h ratios, d yaw.
RESIDUAL_CHANNELS = 7
# A first-stage box learns the residual to the nearest labeled box whose centre is this close.
MATCH_DISTANCE = 1.0
# The side midpoints and the centre, in units of the box's (l/2, w/2).
SAMPLE_POINTS = ((0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))


def apply_residual(boxes: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
    """(..., 7) boxes and (..., 7) residuals -> refined (..., 7) boxes."""
    x, y, z, l, w, h, yaw = boxes.unbind(-1)
    dx, dy, dz, dl, dw, dh, dyaw = residual.unbind(-1)
    diagonal = torch.sqrt(l**2 + w**2)
    c, s = torch.cos(yaw), torch.sin(yaw)
    local_x, local_y = dx * diagonal, dy * diagonal
    return torch.stack(
        [x + local_x * c - local_y * s, y + local_x * s + local_y * c, z + dz * h,
         l * torch.exp(dl), w * torch.exp(dw), h * torch.exp(dh), yaw + dyaw], dim=-1,
    )  # fmt: skip


def residual_targets(rois: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(N, 7) first-stage boxes and their (N, 7) labeled boxes -> (N, 7) residual targets, the
    inverse of apply_residual (yaw difference wrapped to [-pi, pi))."""
    diagonal = np.sqrt(rois[:, 3] ** 2 + rois[:, 4] ** 2)
    c, s = np.cos(rois[:, 6]), np.sin(rois[:, 6])
    offset = truth[:, :2] - rois[:, :2]
    local_x = offset[:, 0] * c + offset[:, 1] * s
    local_y = -offset[:, 0] * s + offset[:, 1] * c
    dyaw = (truth[:, 6] - rois[:, 6] + math.pi) % (2 * math.pi) - math.pi
    return np.column_stack([
        local_x / diagonal, local_y / diagonal, (truth[:, 2] - rois[:, 2]) / rois[:, 5],
        np.log(truth[:, 3] / rois[:, 3]), np.log(truth[:, 4] / rois[:, 4]),
        np.log(truth[:, 5] / rois[:, 5]), dyaw,
    ]).astype(np.float32)  # fmt: skip


def nearest_labels(rois: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(N,) row of the labeled box (M, 7) whose BEV centre is nearest each first-stage box and
    within MATCH_DISTANCE, else -1."""
    return nearest_in_bev(rois, truth, MATCH_DISTANCE)


class BoxRefinement(nn.Module):
    """Features (B, C, h, w) of a BEV grid and detached boxes (B, K, 7) in its frame -> refined
    boxes (B, K, 7). The last layer starts at zero: a fresh refinement returns its input."""

    def __init__(
        self,
        channels: int,
        grid_origin: tuple[float, float],
        cell_size: tuple[float, float],
        hidden: int = 64,
    ) -> None:
        super().__init__()
        self.grid_origin = grid_origin
        self.cell_size = cell_size
        self.mlp = nn.Sequential(
            nn.Linear(channels * len(SAMPLE_POINTS), hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, RESIDUAL_CHANNELS),
        )
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        self.register_buffer("points", torch.tensor(SAMPLE_POINTS), persistent=False)

    def residual(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """(B, K, 7) residuals of detached boxes from detached features."""
        features, boxes = features.detach(), boxes.detach()
        batch, count = boxes.shape[:2]
        height, width = features.shape[-2:]
        c, s = torch.cos(boxes[..., 6:7]), torch.sin(boxes[..., 6:7])
        half_l, half_w = boxes[..., 3:4] / 2, boxes[..., 4:5] / 2
        along, across = self.points[:, 0] * half_l, self.points[:, 1] * half_w  # (B, K, 5)
        x = boxes[..., 0:1] + along * c - across * s
        y = boxes[..., 1:2] + along * s + across * c
        # Metres -> grid_sample's [-1, 1] (align_corners=False: cell centres at (i + 0.5) / n).
        u = (x - self.grid_origin[0]) / (self.cell_size[0] * width) * 2 - 1
        v = (y - self.grid_origin[1]) / (self.cell_size[1] * height) * 2 - 1
        grid = torch.stack([u, v], dim=-1).to(features.dtype)  # (B, K, 5, 2)
        sampled = F.grid_sample(features, grid, mode="bilinear", align_corners=False)
        sampled = sampled.permute(0, 2, 3, 1).reshape(batch, count, -1)  # (B, K, 5 * C)
        return self.mlp(sampled)

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        return apply_residual(boxes.detach(), self.residual(features, boxes))
