"""Training samples: a KITTI-layout frame made ready for both detectors, and their batching.

A sample keeps the frame's calibration, original image size and the augmentation applied, so
detections map back to the un-augmented frame exactly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from detmatch.config import AugmentConfig
from detmatch.constants import IMAGE_MEAN
from detmatch.data.augment import CloudTransform, sample_cloud_transform
from detmatch.data.gt_sampling import (
    DatabaseObject,
    GroundTruthDatabase,
    paste_crops,
    paste_objects,
)
from detmatch.data.kitti import KittiDataset
from detmatch.data.selection import FrameSelection
from detmatch.geometry import bev_cells_in_camera_view, project_boxes_to_image
from detmatch.models.pillars import PillarGrid, Pillars, pillarize
from detmatch.structures import Calibration, Detections, Frame, LabeledBoxes


@dataclass(frozen=True)
class ImageTransform:
    """Original image pixels -> network input pixels: optional horizontal flip of the original
    (width W0), resize to `resized` (w, h) pixels (None: the input size), then the input window
    of input_size taken at `offset` (x, y) of the resized image (a crop; negative offsets pad).
    Multi-scale training draws resized and offset; everything else uses the plain resize."""

    original_size: tuple[int, int]
    input_size: tuple[int, int]
    flipped: bool
    resized: tuple[int, int] | None = None
    offset: tuple[int, int] = (0, 0)

    @property
    def resized_size(self) -> tuple[int, int]:
        return self.input_size if self.resized is None else self.resized

    @property
    def scale(self) -> tuple[float, float]:
        width, height = self.resized_size
        return width / self.original_size[0], height / self.original_size[1]

    def apply(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) xyxy original pixels -> input pixels (not clipped to the window)."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4).copy()
        if self.flipped:
            boxes[:, [0, 2]] = self.original_size[0] - boxes[:, [2, 0]]
        sx, sy = self.scale
        boxes = boxes * np.array([sx, sy, sx, sy])
        if self.offset != (0, 0):
            boxes = boxes - np.array([*self.offset, *self.offset], dtype=np.float64)
        return boxes

    def invert_detections(self, detections: Detections) -> Detections:
        """2D detections, input pixels -> original pixels, clipped to the image."""
        return dataclasses.replace(detections, boxes=self.to_image(detections.boxes))

    def to_image(self, boxes: np.ndarray) -> np.ndarray:
        """Detected (N, 4) boxes in input pixels -> original pixels clipped to the image,
        [0, W - 1] x [0, H - 1] like projected boxes (docs/design.md section 3); the exported 2D
        graph does the same."""
        boxes = self.invert(boxes)
        width, height = self.original_size
        boxes[:, 0::2] = boxes[:, 0::2].clip(0, width - 1)
        boxes[:, 1::2] = boxes[:, 1::2].clip(0, height - 1)
        return boxes

    def invert(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) xyxy input pixels -> original pixels."""
        sx, sy = self.scale
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        if self.offset != (0, 0):
            boxes = boxes + np.array([*self.offset, *self.offset], dtype=np.float64)
        boxes = boxes / np.array([sx, sy, sx, sy])
        if self.flipped:
            boxes[:, [0, 2]] = self.original_size[0] - boxes[:, [2, 0]]
        return boxes

    def clip(self, labels: LabeledBoxes) -> LabeledBoxes:
        """Training boxes in input pixels cut to the input window; boxes left with no area
        are dropped."""
        if self.resized is None:
            return labels
        width, height = self.input_size
        boxes = labels.boxes.copy()
        boxes[:, 0::2] = boxes[:, 0::2].clip(0, width)
        boxes[:, 1::2] = boxes[:, 1::2].clip(0, height)
        keep = (boxes[:, 2] > boxes[:, 0] + 1) & (boxes[:, 3] > boxes[:, 1] + 1)
        return LabeledBoxes(boxes[keep], labels.classes[keep])


def random_image_transform(
    rng: np.random.Generator,
    original_size: tuple[int, int],
    input_size: tuple[int, int],
    flipped: bool,
    scale_range: tuple[float, float],
) -> ImageTransform:
    """Multi-scale training: the input-sized resize scaled by s in scale_range, and a random
    input window of it (cropped, or padded where the rescaled image is smaller)."""
    if scale_range == (1.0, 1.0):
        return ImageTransform(original_size, input_size, flipped)
    s = float(rng.uniform(*scale_range))
    resized = (max(1, round(input_size[0] * s)), max(1, round(input_size[1] * s)))
    offset = tuple(
        int(rng.integers(min(0, r - i), max(0, r - i) + 1))
        for r, i in zip(resized, input_size, strict=True)
    )
    return ImageTransform(original_size, input_size, flipped, resized, offset)


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


# Padding of multi-scale windows: the normalisation's mean pixel (0 after normalising).
PAD_PIXEL = torch.tensor([255.0 * m for m in IMAGE_MEAN]).view(3, 1, 1)


def image_to_tensor(image: np.ndarray, transform: ImageTransform) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, h, w) float32 in [0, 255]: flipped, bilinearly resized and, for
    multi-scale windows, cropped or padded with the mean pixel."""
    tensor = torch.from_numpy(np.array(image, dtype=np.uint8)).permute(2, 0, 1).float()
    if transform.flipped:
        tensor = torch.flip(tensor, dims=[2])
    width, height = transform.resized_size
    if (width, height) != (image.shape[1], image.shape[0]):
        tensor = F.interpolate(
            tensor[None], size=(height, width), mode="bilinear", align_corners=False
        )[0]
    if transform.resized is None:
        return tensor
    (x0, y0), (out_w, out_h) = transform.offset, transform.input_size
    window = PAD_PIXEL.expand(3, out_h, out_w).clone()
    src_x, src_y = (
        slice(max(x0, 0), min(x0 + out_w, width)),
        slice(max(y0, 0), min(y0 + out_h, height)),
    )
    dst_x = slice(src_x.start - x0, src_x.stop - x0)
    dst_y = slice(src_y.start - y0, src_y.stop - y0)
    window[:, dst_y, dst_x] = tensor[:, src_y, src_x]
    return window


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
    flip: bool = False,
    projected_2d: bool = False,
) -> Sample:
    """A frame resized for the 2D detector and pillarized for the 3D one, optionally flipped
    (image and cloud together); see augmented_sample."""
    image = ImageTransform(frame.image_size, tuple(input_size), flip)
    return augmented_sample(frame, classes, grid, image, CloudTransform(flipped=flip), projected_2d)


def augmented_sample(
    frame: Frame,
    classes: tuple[str, ...],
    grid: PillarGrid,
    image: ImageTransform,
    cloud: CloudTransform,
    projected_2d: bool = False,
    pasted: Sequence[DatabaseObject] = (),
) -> Sample:
    """Select the training classes; the image goes through `image` (flip, resize, window),
    the cloud through `cloud` (flip, rotation, scale) after the `pasted` database objects
    replaced its points inside their boxes. projected_2d: 2D boxes are the 3D labels projected
    into the image (docs/design.md section 3, step 1) instead of the annotated 2D boxes. Pasted
    objects join the 3D labels, and the image and 2D labels too when they carry crops."""
    gt_2d, gt_3d = LabeledBoxes.empty(4), LabeledBoxes.empty(7)
    cropped = [o for o in pasted if o.crop is not None]
    if frame.labels is not None:
        names = [str(n) for n in frame.labels.names]
        keep = np.array([n in classes for n in names], dtype=bool)
        class_ids = np.array(
            [classes.index(n) if n in classes else -1 for n in names], dtype=np.int64
        )[keep]
        boxes_3d = frame.labels.boxes_3d.data[keep]
        boxes_2d = frame.labels.boxes_2d.xyxy[keep]
        if projected_2d:
            boxes_2d = project_boxes_to_image(boxes_3d, frame.calib, frame.image_size)
        classes_2d = class_ids
        if cropped:
            pasted_3d = np.stack([o.box for o in cropped])
            pasted_2d = (
                project_boxes_to_image(pasted_3d, frame.calib, frame.image_size)
                if projected_2d
                else np.stack([o.box_2d for o in cropped])
            )
            boxes_2d = np.concatenate([boxes_2d, pasted_2d])
            classes_2d = np.concatenate([class_ids, [o.class_id for o in cropped]])
        gt_2d = image.clip(LabeledBoxes(image.apply(boxes_2d), classes_2d))
        if pasted:
            boxes_3d = np.concatenate([boxes_3d, np.stack([o.box for o in pasted])])
            class_ids = np.concatenate([class_ids, [o.class_id for o in pasted]])
        gt_3d = LabeledBoxes(cloud.apply_boxes(boxes_3d), class_ids)
    pixels = paste_crops(frame.image, cropped) if cropped else frame.image
    points = paste_objects(frame.points, list(pasted))
    if not cloud.is_identity:
        points = cloud.apply_points(points)
    return Sample(
        frame_id=frame.frame_id,
        calib=frame.calib,
        image_transform=image,
        cloud=cloud,
        image=image_to_tensor(pixels, image),
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
    the frame is flipped (image and cloud) with probability flip_probability from a generator
    seeded by (seed, draw), so a replayed step gets the same augmentation. labeled_augment
    (labeled frames only) adds, from a generator seeded by (seed, draw, 2): ground-truth
    database sampling from this split's own frames, global rotation and scale of the cloud,
    and the 2D multi-scale window (detmatch.config.AugmentConfig).
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
        labeled_augment: AugmentConfig | None = None,
        progress: bool = False,
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
        self.labeled_augment = labeled_augment
        self.database = None
        if labeled_augment is not None and labeled_augment.gt_sampling:
            self.database = GroundTruthDatabase.build(
                self.kitti, self.ids, self.classes, labeled_augment.gt_min_points, progress,
                with_images=labeled_augment.gt_sampling_image,
            )  # fmt: skip

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, key: int | tuple[int, int]) -> Sample:
        index, draw = key if isinstance(key, tuple) else (key, key)
        frame = self.kitti.load_frame(self.ids[index], with_labels=self.with_labels)
        flip = False
        if self.augment:
            flip = bool(np.random.default_rng([self.seed, draw]).random() < self.flip_probability)
        if not self.augment or self.labeled_augment is None:
            return make_sample(
                frame, self.classes, self.input_size, self.grid, flip, self.projected_2d
            )
        options = self.labeled_augment
        rng = np.random.default_rng([self.seed, draw, 2])
        cloud = sample_cloud_transform(rng, flip, options.rotation, options.scale)
        image = random_image_transform(
            rng, frame.image_size, self.input_size, flip, options.image_scale
        )
        pasted = []
        if self.database is not None and frame.labels is not None:
            labels = frame.labels
            keep = np.array([str(n) in self.classes for n in labels.names], dtype=bool)
            class_ids = np.array([self.classes.index(str(n)) for n in labels.names[keep]])
            boxes_2d = labels.boxes_2d.xyxy if options.gt_sampling_image else None
            pasted = self.database.sample(
                rng, labels.boxes_3d.data[keep], class_ids, options.gt_sample_counts,
                frame.frame_id, boxes_2d,
            )  # fmt: skip
        return augmented_sample(
            frame, self.classes, self.grid, image, cloud, self.projected_2d, pasted
        )

    def class_presence(self) -> np.ndarray:
        """(frames, classes) bool: which training classes each frame's labels hold."""
        presence = np.zeros((len(self.ids), len(self.classes)), dtype=bool)
        for row, frame_id in enumerate(self.ids):
            names = {str(n) for n in self.kitti.read_objects(frame_id).names}
            presence[row] = [c in names for c in self.classes]
        return presence
