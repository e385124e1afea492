"""Unlabeled frames for teacher-student training: the teacher's weak view and the student's
strong view of the same frame, with every geometric transform recorded (DESIGN.md section 3)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from detmatch.data.augment import CloudTransform, sample_cloud_transform, strong_photometric
from detmatch.data.dataset import Batch, FrameDataset, Sample, collate, collate_pillars
from detmatch.models.pillars import pillarize


@dataclass
class UnlabeledSample:
    """weak: the teacher's view (shared flip and rescale only); student_image: weak image with
    the strong photometric augmentation; student_cloud: un-augmented LiDAR frame -> student
    frame (the shared flip, then rotation and scale); student pillars of the student's cloud."""

    weak: Sample
    student_image: torch.Tensor
    student_cloud: CloudTransform
    student_pillars: tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass
class UnlabeledBatch:
    weak: Batch
    student_images: torch.Tensor
    student_clouds: list[CloudTransform]
    student_pillar_features: torch.Tensor
    student_pillar_coords: torch.Tensor
    student_pillar_counts: torch.Tensor

    def __len__(self) -> int:
        return len(self.weak)

    def to(self, device: torch.device) -> UnlabeledBatch:
        """The batch with its tensors on device (transforms and samples stay numpy)."""
        return dataclasses.replace(
            self,
            weak=self.weak.to(device),
            student_images=self.student_images.to(device, non_blocking=True),
            student_pillar_features=self.student_pillar_features.to(device, non_blocking=True),
            student_pillar_coords=self.student_pillar_coords.to(device, non_blocking=True),
            student_pillar_counts=self.student_pillar_counts.to(device, non_blocking=True),
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
    features, coords, counts = collate_pillars([s.student_pillars for s in samples])
    return UnlabeledBatch(
        weak=collate([s.weak for s in samples]),
        student_images=torch.stack([s.student_image for s in samples]),
        student_clouds=[s.student_cloud for s in samples],
        student_pillar_features=features,
        student_pillar_coords=coords,
        student_pillar_counts=counts,
    )
