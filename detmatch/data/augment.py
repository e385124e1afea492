"""Augmentation for teacher-student training (docs/design.md section 3), with recorded transforms.

- Shared by teacher and student (applied once): horizontal flip of image and point cloud
  together, and the image rescale to the network input (`ImageTransform`).
- Student 3D (strong): global rotation about z and global scale (`CloudTransform`), on top of
  the shared flip. Boxes move between the un-augmented, teacher and student frames exactly.
- Student 2D (strong, photometric only): colour jitter, grayscale, Gaussian blur and three
  random erasings (`strong_photometric`), on (3, H, W) float images in [0, 255].
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from detmatch.constants import IMAGE_MEAN, IMAGE_STD
from detmatch.geometry import limit_period
from detmatch.structures import Detections


@dataclass(frozen=True)
class CloudTransform:
    """Un-augmented LiDAR frame -> augmented frame: optional flip (y -> -y), then rotation by
    `rotation` radians about z, then uniform `scale`."""

    flipped: bool = False
    rotation: float = 0.0
    scale: float = 1.0

    @property
    def is_identity(self) -> bool:
        return not self.flipped and self.rotation == 0.0 and self.scale == 1.0

    def _matrix(self) -> np.ndarray:
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def apply_points(self, points: np.ndarray) -> np.ndarray:
        """(N, >=3) points; extra columns (intensity) pass through."""
        out = np.array(points, dtype=np.float64, copy=True)
        xyz = out[:, :3]
        if self.flipped:
            xyz[:, 1] = -xyz[:, 1]
        out[:, :3] = (xyz @ self._matrix().T) * self.scale
        return out.astype(np.asarray(points).dtype)

    def invert_points(self, points: np.ndarray) -> np.ndarray:
        """(N, >=3) points, augmented -> un-augmented frame (float64; extra columns pass)."""
        out = np.array(points, dtype=np.float64, copy=True)
        xyz = (out[:, :3] / self.scale) @ self._matrix()
        if self.flipped:
            xyz[:, 1] = -xyz[:, 1]
        out[:, :3] = xyz
        return out

    def apply_boxes(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 7) LiDAR boxes, un-augmented -> augmented frame."""
        out = np.asarray(boxes, dtype=np.float64).reshape(-1, 7).copy()
        if self.flipped:
            out[:, 1], out[:, 6] = -out[:, 1], -out[:, 6]
        out[:, :3] = (out[:, :3] @ self._matrix().T) * self.scale
        out[:, 3:6] *= self.scale
        out[:, 6] = limit_period(out[:, 6] + self.rotation)
        return out

    def invert_boxes(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 7) LiDAR boxes, augmented -> un-augmented frame (1/scale, inverse rotation, flip)."""
        out = np.asarray(boxes, dtype=np.float64).reshape(-1, 7).copy()
        out[:, :3] = (out[:, :3] / self.scale) @ self._matrix()
        out[:, 3:6] /= self.scale
        out[:, 6] = limit_period(out[:, 6] - self.rotation)
        if self.flipped:
            out[:, 1], out[:, 6] = -out[:, 1], -out[:, 6]
        return out

    def invert_detections(self, detections: Detections) -> Detections:
        """3D detections, augmented -> un-augmented frame."""
        return dataclasses.replace(detections, boxes=self.invert_boxes(detections.boxes))

    def invert_boxes_torch(self, boxes: torch.Tensor) -> torch.Tensor:
        """Differentiable invert_boxes for (N, 7) tensors (the consistency loss needs it)."""
        rotation = torch.as_tensor(self._matrix(), dtype=boxes.dtype, device=boxes.device)
        centre = (boxes[:, :3] / self.scale) @ rotation
        dims = boxes[:, 3:6] / self.scale
        yaw = boxes[:, 6:7] - self.rotation
        if self.flipped:
            centre = centre * torch.tensor([1.0, -1.0, 1.0], dtype=boxes.dtype, device=boxes.device)
            yaw = -yaw
        return torch.cat([centre, dims, yaw], dim=1)


def sample_cloud_transform(
    rng: np.random.Generator, flipped: bool, max_rotation: float, scale_range: tuple[float, float]
) -> CloudTransform:
    """The student's strong 3D transform: the shared flip, rotation in +-max_rotation, scale."""
    return CloudTransform(
        flipped=flipped,
        rotation=float(rng.uniform(-max_rotation, max_rotation)),
        scale=float(rng.uniform(*scale_range)),
    )


# --- photometric (student 2D) ------------------------------------------------------------------


def _rgb_to_hsv(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) RGB in [0, 1] -> HSV in [0, 1]."""
    r, g, b = image
    maximum, _ = image.max(dim=0)
    minimum, _ = image.min(dim=0)
    delta = maximum - minimum
    safe = torch.where(delta > 0, delta, torch.ones_like(delta))
    hue = torch.where(
        maximum == r,
        ((g - b) / safe) % 6,
        torch.where(maximum == g, (b - r) / safe + 2, (r - g) / safe + 4),
    )
    hue = torch.where(delta > 0, hue / 6, torch.zeros_like(hue))
    saturation = torch.where(maximum > 0, delta / torch.where(maximum > 0, maximum, 1.0), 0.0)
    return torch.stack([hue, saturation, maximum])


def _hsv_to_rgb(image: torch.Tensor) -> torch.Tensor:
    hue, saturation, value = image
    i = torch.floor(hue * 6)
    f = hue * 6 - i
    p, q, t = (
        value * (1 - saturation),
        value * (1 - f * saturation),
        value * (1 - (1 - f) * saturation),
    )
    i = i.long() % 6
    choices = [
        torch.stack([value, t, p]), torch.stack([q, value, p]), torch.stack([p, value, t]),
        torch.stack([p, q, value]), torch.stack([t, p, value]), torch.stack([value, p, q]),
    ]  # fmt: skip
    out = torch.zeros_like(image)
    for k, choice in enumerate(choices):
        out = torch.where((i == k)[None], choice, out)
    return out


def _gray(image: torch.Tensor) -> torch.Tensor:
    return (0.299 * image[0] + 0.587 * image[1] + 0.114 * image[2])[None]


def colour_jitter(
    image: torch.Tensor, rng: np.random.Generator, strength: tuple[float, float, float, float]
) -> torch.Tensor:
    """Brightness, contrast, saturation (factors in [1 - s, 1 + s]) and hue (shift in +-s), in
    random order, on a (3, H, W) image in [0, 1]."""
    brightness, contrast, saturation, hue = strength
    for operation in rng.permutation(4):
        if operation == 0:
            image = image * rng.uniform(1 - brightness, 1 + brightness)
        elif operation == 1:
            mean = _gray(image).mean()
            image = (image - mean) * rng.uniform(1 - contrast, 1 + contrast) + mean
        elif operation == 2:
            gray = _gray(image)
            image = (image - gray) * rng.uniform(1 - saturation, 1 + saturation) + gray
        else:
            hsv = _rgb_to_hsv(image.clamp(0, 1))
            hsv[0] = (hsv[0] + rng.uniform(-hue, hue)) % 1.0
            image = _hsv_to_rgb(hsv)
        image = image.clamp(0, 1)
    return image


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of a (3, H, W) image, kernel radius ceil(3 sigma)."""
    radius = max(1, math.ceil(3 * sigma))
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype)
    kernel = torch.exp(-(offsets**2) / (2 * sigma**2))
    kernel = kernel / kernel.sum()
    x = F.pad(image[None], (radius, radius, 0, 0), mode="reflect")
    x = F.conv2d(x, kernel.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3)
    x = F.pad(x, (0, 0, radius, radius), mode="reflect")
    return F.conv2d(x, kernel.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)[0]


# (probability, area range, aspect-ratio range) of the three random erasings.
ERASINGS = (
    (0.7, (0.05, 0.2), (0.3, 3.3)),
    (0.5, (0.02, 0.2), (0.1, 6.0)),
    (0.3, (0.02, 0.2), (0.05, 8.0)),
)


def random_erase(
    image: torch.Tensor,
    rng: np.random.Generator,
    area: tuple[float, float],
    ratio: tuple[float, float],
) -> torch.Tensor:
    """Fill one random rectangle of the given area fraction and log-uniform aspect ratio with
    random values (torchvision's RandomErasing with value='random', up to 10 tries)."""
    _, height, width = image.shape
    for _ in range(10):
        target = rng.uniform(*area) * height * width
        aspect = math.exp(rng.uniform(math.log(ratio[0]), math.log(ratio[1])))
        h = int(round(math.sqrt(target * aspect)))
        w = int(round(math.sqrt(target / aspect)))
        if 0 < h < height and 0 < w < width:
            top, left = int(rng.integers(0, height - h + 1)), int(rng.integers(0, width - w + 1))
            image = image.clone()
            noise = torch.from_numpy(rng.standard_normal((3, h, w)).astype(np.float32))
            image[:, top : top + h, left : left + w] = noise.to(image.dtype)
            return image
    return image


def strong_photometric(image: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """The student 2D augmentation of docs/design.md section 3 on a (3, H, W) image in [0, 255].
    Random erasing fills with standard-normal noise in normalised units, as torchvision does
    after normalisation; here it is mapped back to [0, 255] pixel units."""
    x = image / 255.0
    if rng.random() < 0.8:
        x = colour_jitter(x, rng, (0.4, 0.4, 0.4, 0.1))
    if rng.random() < 0.2:
        x = _gray(x).expand(3, -1, -1).clone()
    if rng.random() < 0.5:
        x = gaussian_blur(x, float(rng.uniform(0.1, 2.0)))
    x = x * 255.0
    mean = torch.tensor([255.0 * m for m in IMAGE_MEAN]).view(3, 1, 1)
    std = torch.tensor([255.0 * s for s in IMAGE_STD]).view(3, 1, 1)
    normalised = (x - mean) / std
    for probability, area, ratio in ERASINGS:
        if rng.random() < probability:
            normalised = random_erase(normalised, rng, area, ratio)
    return normalised * std + mean
