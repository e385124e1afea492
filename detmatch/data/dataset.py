"""Training samples: a KITTI-layout frame made ready for both detectors, and their batching.

A sample keeps the frame's calibration, original image size and the augmentation applied, so
detections map back to the un-augmented frame exactly.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from detmatch.data.kitti import KittiDataset
from detmatch.geometry import project_boxes_to_image
from detmatch.models.pillars import PillarGrid, pillarize
from detmatch.structures import Calibration, Frame


@dataclass(frozen=True)
class ImageTransform:
    """Original image pixels -> network input pixels: optional horizontal flip of the original
    (width W0), then scale by (sx, sy)."""

    original_size: tuple[int, int]
    input_size: tuple[int, int]
    flipped: bool

    @property
    def scale(self) -> tuple[float, float]:
        return (
            self.input_size[0] / self.original_size[0],
            self.input_size[1] / self.original_size[1],
        )

    def apply(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) xyxy original pixels -> input pixels."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4).copy()
        if self.flipped:
            boxes[:, [0, 2]] = self.original_size[0] - boxes[:, [2, 0]]
        sx, sy = self.scale
        return boxes * np.array([sx, sy, sx, sy])

    def invert(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) xyxy input pixels -> original pixels."""
        sx, sy = self.scale
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4) / np.array([sx, sy, sx, sy])
        if self.flipped:
            boxes[:, [0, 2]] = self.original_size[0] - boxes[:, [2, 0]]
        return boxes


def flip_boxes_3d(boxes: np.ndarray) -> np.ndarray:
    """Mirror (N, 7) LiDAR boxes across the x-z plane (y -> -y, yaw -> -yaw); its own inverse."""
    flipped = np.asarray(boxes, dtype=np.float64).reshape(-1, 7).copy()
    flipped[:, 1] = -flipped[:, 1]
    flipped[:, 6] = -flipped[:, 6]
    return flipped


def flip_points(points: np.ndarray) -> np.ndarray:
    flipped = np.array(points, dtype=np.float32, copy=True)
    flipped[:, 1] = -flipped[:, 1]
    return flipped


def image_to_tensor(image: np.ndarray, transform: ImageTransform) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, h, w) float32 in [0, 255], flipped and bilinearly resized."""
    tensor = torch.from_numpy(np.array(image, dtype=np.uint8)).permute(2, 0, 1).float()
    if transform.flipped:
        tensor = torch.flip(tensor, dims=[2])
    if tuple(transform.input_size) != (image.shape[1], image.shape[0]):
        tensor = F.interpolate(
            tensor[None],
            size=(transform.input_size[1], transform.input_size[0]),
            mode="bilinear",
            align_corners=False,
        )[0]
    return tensor


@dataclass
class Sample:
    """One frame ready for both detectors (see ImageTransform / flip_boxes_3d for frames).

    image: (3, h, w) network input; boxes_2d: (N, 4) input pixels; boxes_3d: (M, 7) LiDAR frame
    after the flip; pillars: (P, M, 9) features, (P, 2) coords, (P,) counts; points: (N, 4)
    LiDAR points after the flip.
    """

    frame_id: str
    calib: Calibration
    image_transform: ImageTransform
    image: torch.Tensor
    boxes_2d: np.ndarray
    classes_2d: np.ndarray
    boxes_3d: np.ndarray
    classes_3d: np.ndarray
    pillar_features: np.ndarray
    pillar_coords: np.ndarray
    pillar_counts: np.ndarray
    points: np.ndarray

    @property
    def flipped(self) -> bool:
        return self.image_transform.flipped


@dataclass
class Batch:
    frame_ids: list[str]
    samples: list[Sample]
    images: torch.Tensor
    pillar_features: torch.Tensor
    pillar_coords: torch.Tensor
    pillar_counts: torch.Tensor

    def __len__(self) -> int:
        return len(self.samples)

    def to(self, device: torch.device) -> Batch:
        """The batch with its tensors on device (the samples stay numpy)."""
        return dataclasses.replace(
            self,
            images=self.images.to(device, non_blocking=True),
            pillar_features=self.pillar_features.to(device, non_blocking=True),
            pillar_coords=self.pillar_coords.to(device, non_blocking=True),
            pillar_counts=self.pillar_counts.to(device, non_blocking=True),
        )


def make_sample(
    frame: Frame,
    classes: tuple[str, ...],
    input_size: tuple[int, int],
    grid: PillarGrid,
    flip: bool,
    projected_2d: bool = False,
) -> Sample:
    """Select the training classes, flip image and point cloud together if asked, resize the
    image and pillarize the points. projected_2d: 2D boxes are the 3D labels projected into
    the image (DESIGN.md section 3, step 1) instead of the annotated 2D boxes."""
    transform = ImageTransform(frame.image_size, tuple(input_size), flip)
    boxes_2d, classes_2d = np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    boxes_3d, classes_3d = np.zeros((0, 7)), np.zeros(0, dtype=np.int64)
    if frame.labels is not None:
        names = [str(n) for n in frame.labels.names]
        keep = np.array([n in classes for n in names], dtype=bool)
        class_ids = np.array(
            [classes.index(n) if n in classes else -1 for n in names], dtype=np.int64
        )
        boxes_3d, classes_3d = frame.labels.boxes_3d.data[keep], class_ids[keep]
        boxes_2d = frame.labels.boxes_2d.xyxy[keep]
        if projected_2d:
            boxes_2d = project_boxes_to_image(boxes_3d, frame.calib, frame.image_size)
        boxes_2d, classes_2d = transform.apply(boxes_2d), class_ids[keep]
        if flip:
            boxes_3d = flip_boxes_3d(boxes_3d)
    points = flip_points(frame.points) if flip else frame.points
    features, coords, counts = pillarize(points, grid)
    return Sample(
        frame_id=frame.frame_id,
        calib=frame.calib,
        image_transform=transform,
        image=image_to_tensor(frame.image, transform),
        boxes_2d=boxes_2d,
        classes_2d=classes_2d,
        boxes_3d=boxes_3d,
        classes_3d=classes_3d,
        pillar_features=features,
        pillar_coords=coords,
        pillar_counts=counts,
        points=points,
    )


def collate_pillars(
    pillars: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-frame (features, coords (P, 2), counts) -> batched tensors, coords with the batch
    index prepended."""
    coords = [
        np.concatenate([np.full((len(c), 1), b, dtype=np.int64), c], axis=1)
        for b, (_, c, _) in enumerate(pillars)
    ]
    return (
        torch.from_numpy(np.concatenate([f for f, _, _ in pillars])),
        torch.from_numpy(np.concatenate(coords)),
        torch.from_numpy(np.concatenate([n for _, _, n in pillars])),
    )


def collate(samples: list[Sample]) -> Batch:
    """Stack images; concatenate pillars with their batch index as the first coordinate."""
    features, coords, counts = collate_pillars(
        [(s.pillar_features, s.pillar_coords, s.pillar_counts) for s in samples]
    )
    return Batch(
        frame_ids=[s.frame_id for s in samples],
        samples=samples,
        images=torch.stack([s.image for s in samples]),
        pillar_features=features,
        pillar_coords=coords,
        pillar_counts=counts,
    )


class FrameDataset(torch.utils.data.Dataset):
    """Frames of one ImageSets split as Samples.

    Indexed by a frame index, or by (frame index, draw) as StepSampler yields: with augment,
    the frame is flipped with probability flip_probability from a generator seeded by
    (seed, draw), so a replayed step gets the same augmentation.
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        classes: tuple[str, ...],
        input_size: tuple[int, int],
        grid: PillarGrid,
        augment: bool = False,
        flip_probability: float = 0.5,
        seed: int = 0,
        with_labels: bool = True,
        projected_2d: bool = False,
    ) -> None:
        self.kitti = KittiDataset(root)
        self.ids = self.kitti.ids(split)
        if not self.ids:
            raise ValueError(f"split {split!r} of {root} has no frames")
        self.classes = tuple(classes)
        self.input_size = tuple(input_size)
        self.grid = grid
        self.augment = augment
        self.flip_probability = flip_probability
        self.seed = seed
        self.with_labels = with_labels
        self.projected_2d = projected_2d

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, key: int | tuple[int, int]) -> Sample:
        index, draw = key if isinstance(key, tuple) else (key, key)
        frame = self.kitti.load_frame(self.ids[index], with_labels=self.with_labels)
        flip = False
        if self.augment:
            flip = bool(np.random.default_rng([self.seed, draw]).random() < self.flip_probability)
        return make_sample(frame, self.classes, self.input_size, self.grid, flip, self.projected_2d)
