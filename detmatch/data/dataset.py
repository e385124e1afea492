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

from detmatch.data.augment import CloudTransform
from detmatch.data.kitti import KittiDataset
from detmatch.data.selection import FrameSelection
from detmatch.geometry import bev_cells_in_camera_view, project_boxes_to_image
from detmatch.models.pillars import PillarGrid, Pillars, pillarize
from detmatch.structures import Calibration, Detections, Frame, LabeledBoxes


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

    def invert_detections(self, detections: Detections) -> Detections:
        """2D detections, input pixels -> original pixels."""
        return dataclasses.replace(detections, boxes=self.invert(detections.boxes))

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


@dataclass(frozen=True)
class CameraView:
    """Where a frame's 3D labels exist: the camera's view (a `LabelledArea` of the 3D
    detector's contract). cloud maps the un-augmented LiDAR frame to the detector's input."""

    calib: Calibration
    image_size: tuple[int, int]
    cloud: CloudTransform

    def contains_bev(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) x, y metres in the detector's frame -> (N,) bool, by
        `geometry.bev_cells_in_camera_view` in the un-augmented frame."""
        points = np.column_stack([xy, np.zeros(len(xy))])
        unaugmented = self.cloud.invert_points(points)[:, :2]
        return bev_cells_in_camera_view(unaugmented, self.calib, self.image_size)


@dataclass
class Sample:
    """One frame ready for both detectors (see ImageTransform and CloudTransform for frames).

    image: (3, h, w) network input; gt_2d: boxes in input pixels; gt_3d: LiDAR boxes in the
    augmented frame; pillars: of the augmented cloud; points: (N, 4) the augmented cloud.
    """

    frame_id: str
    calib: Calibration
    image_transform: ImageTransform
    cloud: CloudTransform
    image: torch.Tensor
    gt_2d: LabeledBoxes
    gt_3d: LabeledBoxes
    pillars: Pillars
    points: np.ndarray

    @property
    def flipped(self) -> bool:
        return self.image_transform.flipped

    @property
    def camera_view(self) -> CameraView:
        """Where this frame's 3D labels exist, for the 3D detector's targets."""
        return CameraView(self.calib, self.image_transform.original_size, self.cloud)


@dataclass
class Batch:
    frame_ids: list[str]
    samples: list[Sample]
    images: torch.Tensor
    pillars: Pillars

    def __len__(self) -> int:
        return len(self.samples)

    def to(self, device: torch.device) -> Batch:
        """The batch with its tensors on device (the samples stay numpy)."""
        return dataclasses.replace(
            self, images=self.images.to(device, non_blocking=True), pillars=self.pillars.to(device)
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
    cloud = CloudTransform(flipped=flip)
    gt_2d, gt_3d = LabeledBoxes.empty(4), LabeledBoxes.empty(7)
    if frame.labels is not None:
        names = [str(n) for n in frame.labels.names]
        keep = np.array([n in classes for n in names], dtype=bool)
        class_ids = np.array(
            [classes.index(n) if n in classes else -1 for n in names], dtype=np.int64
        )
        boxes_3d = frame.labels.boxes_3d.data[keep]
        boxes_2d = frame.labels.boxes_2d.xyxy[keep]
        if projected_2d:
            boxes_2d = project_boxes_to_image(boxes_3d, frame.calib, frame.image_size)
        gt_2d = LabeledBoxes(transform.apply(boxes_2d), class_ids[keep])
        gt_3d = LabeledBoxes(flip_boxes_3d(boxes_3d) if flip else boxes_3d, class_ids[keep])
    points = flip_points(frame.points) if flip else frame.points
    return Sample(
        frame_id=frame.frame_id,
        calib=frame.calib,
        image_transform=transform,
        cloud=cloud,
        image=image_to_tensor(frame.image, transform),
        gt_2d=gt_2d,
        gt_3d=gt_3d,
        pillars=pillarize(points, grid),
        points=points,
    )


def collate_pillars(frames: list[Pillars]) -> Pillars:
    """One-frame pillars -> a batch's tensors, coords (P, 3) with the frame index first."""
    coords = [
        np.concatenate([np.full((len(p.coords), 1), b, dtype=np.int64), p.coords], axis=1)
        for b, p in enumerate(frames)
    ]
    return Pillars(
        torch.from_numpy(np.concatenate([p.features for p in frames])),
        torch.from_numpy(np.concatenate(coords)),
        torch.from_numpy(np.concatenate([p.counts for p in frames])),
        batch_size=len(frames),
    )


def cat_pillars(first: Pillars, second: Pillars) -> Pillars:
    """Two batches' pillars as one batch: second's frames follow first's."""
    shifted = second.coords.clone()
    shifted[:, 0] += first.batch_size
    return Pillars(
        torch.cat([first.features, second.features]),
        torch.cat([first.coords, shifted]),
        torch.cat([first.counts, second.counts]),
        batch_size=first.batch_size + second.batch_size,
    )


def collate(samples: list[Sample]) -> Batch:
    """Stack images; concatenate pillars with their batch index as the first coordinate."""
    return Batch(
        frame_ids=[s.frame_id for s in samples],
        samples=samples,
        images=torch.stack([s.image for s in samples]),
        pillars=collate_pillars([s.pillars for s in samples]),
    )


class FrameDataset(torch.utils.data.Dataset):
    """Frames of one ImageSets split (or of a FrameSelection) as Samples.

    Indexed by a frame index, or by (frame index, draw) as StepSampler yields: with augment,
    the frame is flipped with probability flip_probability from a generator seeded by
    (seed, draw), so a replayed step gets the same augmentation.
    """

    def __init__(
        self,
        root: str | Path,
        split: str | FrameSelection,
        classes: tuple[str, ...],
        input_size: tuple[int, int],
        grid: PillarGrid,
        augment: bool = False,
        flip_probability: float = 0.5,
        seed: int = 0,
        with_labels: bool = True,
        projected_2d: bool = False,
    ) -> None:
        if isinstance(split, FrameSelection):
            self.kitti, self.ids = split.resolve(root)
        else:
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
