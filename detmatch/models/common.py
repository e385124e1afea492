"""Building blocks shared by the 2D and 3D detectors: conv blocks, heatmap targets, focal loss and
peak decoding that exports to ONNX (max-pool peaks + top-k; no NMS custom op)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


def tensor_like(array: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """A numpy target as a tensor on the device of the prediction it is compared with."""
    return torch.from_numpy(array).to(like.device, non_blocking=True)


def conv_bn_relu(in_channels: int, out_channels: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


class ResidualBlock(nn.Module):
    """Two 3x3 conv-BN layers with an identity shortcut."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)), inplace=True)
        return F.relu(self.bn2(self.conv2(out)) + x, inplace=True)


def stage(in_channels: int, out_channels: int, depth: int, stride: int) -> nn.Sequential:
    """A strided conv followed by `depth` residual blocks."""
    layers: list[nn.Module] = [conv_bn_relu(in_channels, out_channels, stride)]
    layers += [ResidualBlock(out_channels) for _ in range(depth)]
    return nn.Sequential(*layers)


def head(in_channels: int, width: int, out_channels: int, bias: float = 0.0) -> nn.Sequential:
    """3x3 conv + ReLU + 1x1 conv; the final bias initialises e.g. heatmap logits low."""
    layers = nn.Sequential(
        nn.Conv2d(in_channels, width, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(width, out_channels, 1),
    )
    nn.init.constant_(layers[-1].bias, bias)
    return layers


# Focal-loss heatmaps start near this probability (CenterNet's -2.19 logit).
HEATMAP_PRIOR_BIAS = -math.log((1 - 0.1) / 0.1)


# --- targets -----------------------------------------------------------------------------------


def gaussian_radius(height: float, width: float, min_overlap: float) -> float:
    """CenterNet's radius: the largest corner shift keeping IoU >= min_overlap (in cells)."""
    a1, b1 = 1.0, height + width
    c1 = width * height * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1**2 - 4 * a1 * c1)) / 2
    a2, b2 = 4.0, 2 * (height + width)
    c2 = (1 - min_overlap) * width * height
    r2 = (b2 + math.sqrt(b2**2 - 4 * a2 * c2)) / 2
    a3, b3 = 4 * min_overlap, -2 * min_overlap * (height + width)
    c3 = (min_overlap - 1) * width * height
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def draw_gaussian(heatmap: np.ndarray, centre_x: int, centre_y: int, radius: int) -> None:
    """Splat a Gaussian peak of value 1 at (centre_x, centre_y) into (H, W) heatmap (max-merge)."""
    diameter = 2 * radius + 1
    sigma = diameter / 6
    offsets = np.arange(-radius, radius + 1)
    gaussian = np.exp(-(offsets[None, :] ** 2 + offsets[:, None] ** 2) / (2 * sigma**2))
    height, width = heatmap.shape
    left, right = min(centre_x, radius), min(width - centre_x, radius + 1)
    top, bottom = min(centre_y, radius), min(height - centre_y, radius + 1)
    if left + right <= 0 or top + bottom <= 0:
        return
    region = heatmap[centre_y - top : centre_y + bottom, centre_x - left : centre_x + right]
    patch = gaussian[radius - top : radius + bottom, radius - left : radius + right]
    np.maximum(region, patch, out=region)


# --- losses ------------------------------------------------------------------------------------


def heatmap_focal_loss(
    logits: torch.Tensor,
    target: torch.Tensor,
    negative_mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4), summed and divided by the
    number of peaks. logits, target: (B, C, H, W); target peaks
    are exactly 1. negative_mask (B, 1, H, W), if given, is 0 where background must not be
    learned (no labels there)."""
    probability = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    positive = target.eq(1).float()
    negative_weight = torch.pow(1 - target, 4)
    if negative_mask is not None:
        negative_weight = negative_weight * negative_mask
    positive_loss = torch.log(probability) * torch.pow(1 - probability, 2) * positive
    negative_loss = (
        torch.log(1 - probability) * torch.pow(probability, 2) * negative_weight * (1 - positive)
    )
    return -(positive_loss.sum() + negative_loss.sum()) / positive.sum().clamp(min=1.0)


def sigmoid_focal_loss(
    logits: torch.Tensor, target: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0
) -> torch.Tensor:
    """RetinaNet focal loss, elementwise (no reduction). target in {0, 1}, same shape."""
    probability = torch.sigmoid(logits)
    ce = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    p_t = probability * target + (1 - probability) * (1 - target)
    alpha_t = alpha * target + (1 - alpha) * (1 - target)
    return alpha_t * ce * (1 - p_t) ** gamma


# --- decoding ----------------------------------------------------------------------------------


def heatmap_peaks(
    heat: torch.Tensor, k: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Top-k local maxima of a (B, C, H, W) probability heatmap.

    Returns scores (B, k), classes (B, k) int64, flat pixel index (B, k) int64 into H * W, and
    the per-class probability vectors at those pixels (B, k, C). Peaks are 3x3 max-pool maxima
    (the NMS), so the whole decode exports to ONNX as MaxPool + TopK + Gather.
    """
    batch, num_classes, height, width = heat.shape
    pooled = F.max_pool2d(heat, 3, stride=1, padding=1)
    peaks = heat * (pooled == heat).to(heat.dtype)
    k = min(k, num_classes * height * width)
    scores, flat = torch.topk(peaks.reshape(batch, -1), k)
    classes = torch.div(flat, height * width, rounding_mode="floor")
    pixel = flat - classes * (height * width)
    all_classes = heat.reshape(batch, num_classes, height * width)
    gather_index = pixel.unsqueeze(1).expand(batch, num_classes, k)
    probabilities = torch.gather(all_classes, 2, gather_index).transpose(1, 2)
    return scores, classes, pixel, probabilities


def gather_at(feature: torch.Tensor, pixel: torch.Tensor) -> torch.Tensor:
    """(B, D, H, W) feature map, (B, k) flat pixel indices -> (B, k, D)."""
    batch, depth = feature.shape[:2]
    flat = feature.reshape(batch, depth, -1)
    return torch.gather(flat, 2, pixel.unsqueeze(1).expand(batch, depth, pixel.shape[1])).transpose(
        1, 2
    )
