"""Unlabeled frames for teacher-student training: the teacher's weak view and the student's
strong view of the same frame, with every geometric transform recorded (docs/design.md
section 3)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from detmatch.data.augment import CloudTransform, sample_cloud_transform, strong_photometric
from detmatch.data.dataset import (
    Batch,
    FrameDataset,
    Sample,
    cat_pillars,
    collate,
    collate_pillars,
)
from detmatch.models.pillars import Pillars, pillarize
from detmatch.structures import LabeledBoxes


@dataclass
class UnlabeledSample:
    """weak: the teacher's view (shared flip and rescale only); student_image: weak image with
    the strong photometric augmentation; student_cloud: un-augmented LiDAR frame -> student
    frame (the shared flip, then rotation and scale); student pillars of the student's cloud."""

    weak: Sample
    student_image: torch.Tensor
    student_cloud: CloudTransform
    student_pillars: Pillars


@dataclass
class UnlabeledBatch:
    weak: Batch
    student_images: torch.Tensor
    student_clouds: list[CloudTransform]
    student_pillars: Pillars

    def __len__(self) -> int:
        return len(self.weak)

    def student_inputs(self, labeled: Batch) -> tuple[torch.Tensor, Pillars]:
        """The students' batch: labeled frames first, then the strong unlabeled views."""
        images = torch.cat([labeled.images, self.student_images])
        return images, cat_pillars(labeled.pillars, self.student_pillars)

    def to_student_frames(
        self, labels_2d: list[LabeledBoxes], labels_3d: list[LabeledBoxes]
    ) -> tuple[list[LabeledBoxes], list[LabeledBoxes]]:
        """Per-frame labels in the un-augmented frame (2D original pixels, 3D LiDAR) -> the
        students' frames (2D input pixels, 3D the strong view's cloud)."""
        moved_2d = [
            labels.map_boxes(sample.image_transform.apply)
            for labels, sample in zip(labels_2d, self.weak.samples, strict=True)
        ]
        moved_3d = [
            labels.map_boxes(cloud.apply_boxes)
            for labels, cloud in zip(labels_3d, self.student_clouds, strict=True)
        ]
        return moved_2d, moved_3d

    def to(self, device: torch.device) -> UnlabeledBatch:
        """The batch with its tensors on device (transforms and samples stay numpy)."""
        return dataclasses.replace(
            self,
            weak=self.weak.to(device),
            student_images=self.student_images.to(device, non_blocking=True),
            student_pillars=self.student_pillars.to(device),
        )


class UnlabeledDataset(torch.utils.data.Dataset):
    """Wraps a FrameDataset (augment on: the shared flip) and adds the student's strong view.
    Indexed by (frame index, draw) like FrameDataset; the strong augmentation draws from a
    generator seeded by (seed, draw, 1), so a replayed step gets the same views."""

    def __init__(
        self,
        frames: FrameDataset,
        max_rotation: float,
        scale_range: tuple[float, float],
        photometric: bool = True,
    ) -> None:
        self.frames = frames
        self.max_rotation = max_rotation
        self.scale_range = scale_range
        self.photometric = photometric

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, key: int | tuple[int, int]) -> UnlabeledSample:
        index, draw = key if isinstance(key, tuple) else (key, key)
        weak = self.frames[(index, draw)]
        rng = np.random.default_rng([self.frames.seed, draw, 1])
        cloud = sample_cloud_transform(rng, weak.flipped, self.max_rotation, self.scale_range)
        # weak.points are already flipped; apply only the rotation and scale on top.
        extra = CloudTransform(False, cloud.rotation, cloud.scale)
        student_points = extra.apply_points(weak.points)
        image = strong_photometric(weak.image, rng) if self.photometric else weak.image
        return UnlabeledSample(
            weak=weak,
            student_image=image,
            student_cloud=cloud,
            student_pillars=pillarize(student_points, self.frames.grid),
        )


def collate_unlabeled(samples: list[UnlabeledSample]) -> UnlabeledBatch:
    return UnlabeledBatch(
        weak=collate([s.weak for s in samples]),
        student_images=torch.stack([s.student_image for s in samples]),
        student_clouds=[s.student_cloud for s in samples],
        student_pillars=collate_pillars([s.student_pillars for s in samples]),
    )
