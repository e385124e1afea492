"""Typed, frozen structures shared by training, evaluation and serving.

Everything here is numpy: the labeling service uses these types and must not import torch.
Models convert to tensors at their own boundary.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


def _as_float_array(name: str, value: np.ndarray, shape: tuple[int | None, ...]) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(array.shape, shape, strict=True)
    ):
        shown = ", ".join("N" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} expects shape ({shown}), got {tuple(array.shape)}")
    return array


@dataclass(frozen=True)
class Boxes2D:
    """Pixels of the original (un-augmented) image: (N, 4) x1, y1, x2, y2."""

    xyxy: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "xyxy", _as_float_array("Boxes2D", self.xyxy, (None, 4)))

    def __len__(self) -> int:
        return self.xyxy.shape[0]

    def __getitem__(self, index: np.ndarray | slice | int) -> Boxes2D:
        return Boxes2D(self.xyxy[np.atleast_1d(index) if np.isscalar(index) else index])

    @property
    def widths(self) -> np.ndarray:
        return self.xyxy[:, 2] - self.xyxy[:, 0]

    @property
    def heights(self) -> np.ndarray:
        return self.xyxy[:, 3] - self.xyxy[:, 1]

    @staticmethod
    def empty() -> Boxes2D:
        return Boxes2D(np.zeros((0, 4)))


@dataclass(frozen=True)
class Boxes3D:
    """LiDAR frame, gravity centre, metres and radians: (N, 7) x, y, z, l, w, h, yaw.

    x forward, y left, z up; yaw about +z, measured from +x; l lies along the heading.
    """

    data: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "data", _as_float_array("Boxes3D", self.data, (None, 7)))

    def __len__(self) -> int:
        return self.data.shape[0]

    def __getitem__(self, index: np.ndarray | slice | int) -> Boxes3D:
        return Boxes3D(self.data[np.atleast_1d(index) if np.isscalar(index) else index])

    @property
    def centers(self) -> np.ndarray:
        return self.data[:, 0:3]

    @property
    def dims(self) -> np.ndarray:
        """(N, 3) l, w, h in metres."""
        return self.data[:, 3:6]

    @property
    def yaw(self) -> np.ndarray:
        return self.data[:, 6]

    @staticmethod
    def empty() -> Boxes3D:
        return Boxes3D(np.zeros((0, 7)))


@dataclass(frozen=True)
class Calibration:
    """KITTI calibration of one frame.

    P2: (3, 4) rectified camera 2 projection; R0_rect: (3, 3) rectifying rotation;
    Tr_velo_to_cam: (3, 4) LiDAR -> reference camera.
    lidar -> image = P2 . R0_rect . Tr_velo_to_cam.
    """

    P2: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "P2", _as_float_array("Calibration.P2", self.P2, (3, 4)))
        object.__setattr__(
            self, "R0_rect", _as_float_array("Calibration.R0_rect", self.R0_rect, (3, 3))
        )
        object.__setattr__(
            self,
            "Tr_velo_to_cam",
            _as_float_array("Calibration.Tr_velo_to_cam", self.Tr_velo_to_cam, (3, 4)),
        )
        for name in ("P2", "R0_rect", "Tr_velo_to_cam"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"Calibration.{name} holds NaN or Inf")

    @property
    def lidar_to_rect(self) -> np.ndarray:
        """(4, 4) homogeneous LiDAR -> rectified camera transform."""
        tr = np.eye(4)
        tr[:3, :4] = self.Tr_velo_to_cam
        r0 = np.eye(4)
        r0[:3, :3] = self.R0_rect
        return r0 @ tr

    @property
    def lidar_to_image(self) -> np.ndarray:
        """(3, 4) homogeneous LiDAR -> image projection, P2 . R0_rect . Tr_velo_to_cam."""
        return self.P2 @ self.lidar_to_rect

    @staticmethod
    def from_flat(p2: np.ndarray, r0_rect: np.ndarray, tr_velo_to_cam: np.ndarray) -> Calibration:
        """From row-major flat arrays of 12, 9 and 12 numbers (the service's wire format)."""
        for name, values, size in (
            ("P2", p2, 12),
            ("R0_rect", r0_rect, 9),
            ("Tr_velo_to_cam", tr_velo_to_cam, 12),
        ):
            if np.asarray(values).size != size:
                raise ValueError(f"{name} needs {size} numbers, got {np.asarray(values).size}")
        return Calibration(
            np.asarray(p2, dtype=np.float64).reshape(3, 4),
            np.asarray(r0_rect, dtype=np.float64).reshape(3, 3),
            np.asarray(tr_velo_to_cam, dtype=np.float64).reshape(3, 4),
        )


@dataclass(frozen=True)
class Labels:
    """Annotated objects of one frame in the project's conventions.

    names: (N,) class names as in KITTI (Car, Pedestrian, ..., DontCare);
    boxes_2d: annotated 2D boxes; boxes_3d: LiDAR-frame boxes (DontCare rows hold zeros);
    truncated: (N,) in [0, 1]; occluded: (N,) KITTI levels 0..3 (-1 for DontCare);
    alpha: (N,) observation angle; scores: (N,) detection scores, or None for ground truth.
    """

    names: np.ndarray
    boxes_2d: Boxes2D
    boxes_3d: Boxes3D
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    scores: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", np.asarray(self.names, dtype=object).reshape(-1))
        n = len(self.names)
        object.__setattr__(self, "truncated", np.asarray(self.truncated, dtype=np.float64))
        object.__setattr__(self, "occluded", np.asarray(self.occluded, dtype=np.int64))
        object.__setattr__(self, "alpha", np.asarray(self.alpha, dtype=np.float64))
        if self.scores is not None:
            object.__setattr__(self, "scores", np.asarray(self.scores, dtype=np.float64))
        for name in ("boxes_2d", "boxes_3d", "truncated", "occluded", "alpha", "scores"):
            value = getattr(self, name)
            if value is not None and len(value) != n:
                raise ValueError(f"Labels.{name} has {len(value)} rows, names has {n}")

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: np.ndarray | slice) -> Labels:
        return Labels(
            names=self.names[index],
            boxes_2d=self.boxes_2d[index],
            boxes_3d=self.boxes_3d[index],
            truncated=self.truncated[index],
            occluded=self.occluded[index],
            alpha=self.alpha[index],
            scores=None if self.scores is None else self.scores[index],
        )

    @staticmethod
    def empty(with_scores: bool = False) -> Labels:
        return Labels(
            names=np.zeros(0, dtype=object),
            boxes_2d=Boxes2D.empty(),
            boxes_3d=Boxes3D.empty(),
            truncated=np.zeros(0),
            occluded=np.zeros(0, dtype=np.int64),
            alpha=np.zeros(0),
            scores=np.zeros(0) if with_scores else None,
        )


@dataclass(frozen=True)
class Frame:
    """One paired camera + LiDAR frame.

    image: (H, W, 3) uint8 RGB; points: (N, 4) float32 LiDAR x, y, z, intensity;
    labels: ground truth when known.
    """

    frame_id: str
    image: np.ndarray
    points: np.ndarray
    calib: Calibration
    labels: Labels | None = field(default=None)

    def __post_init__(self) -> None:
        if self.image.ndim != 3 or self.image.shape[2] != 3 or self.image.dtype != np.uint8:
            raise ValueError(
                f"Frame.image expects (H, W, 3) uint8, got {self.image.shape} {self.image.dtype}"
            )
        if self.points.ndim != 2 or self.points.shape[1] != 4:
            raise ValueError(f"Frame.points expects (N, 4), got {tuple(self.points.shape)}")

    @property
    def image_size(self) -> tuple[int, int]:
        """(W, H) in pixels."""
        return int(self.image.shape[1]), int(self.image.shape[0])


@dataclass(frozen=True)
class Detections:
    """One frame's detections of one modality, in the un-augmented frame.

    boxes: (N, 4) xyxy original-image pixels (2D) or (N, 7) LiDAR boxes (3D);
    scores: (N,) max class probability; classes: (N,) class ids; probabilities: (N, C).
    """

    boxes: np.ndarray
    scores: np.ndarray
    classes: np.ndarray
    probabilities: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.scores)
        if self.boxes.ndim != 2 or self.boxes.shape[1] not in (4, 7) or len(self.boxes) != n:
            raise ValueError(f"Detections.boxes expects (N, 4) or (N, 7), got {self.boxes.shape}")
        if len(self.classes) != n or self.probabilities.ndim != 2 or len(self.probabilities) != n:
            raise ValueError("Detections fields disagree on the number of boxes")

    def __len__(self) -> int:
        return len(self.scores)

    def __getitem__(self, index: np.ndarray | slice) -> Detections:
        return Detections(
            self.boxes[index], self.scores[index], self.classes[index], self.probabilities[index]
        )


@dataclass(frozen=True)
class LabeledBoxes:
    """Objects a detector learns from, in the frame of its input: ground truth or pseudo-labels.

    boxes: (N, 4) xyxy pixels (2D) or (N, 7) LiDAR boxes (3D); classes: (N,) int64 class ids;
    probabilities: (N, C) a teacher's class probabilities for pseudo-labels, None for ground
    truth.
    """

    boxes: np.ndarray
    classes: np.ndarray
    probabilities: np.ndarray | None = None

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes, dtype=np.float64)
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "classes", np.asarray(self.classes, dtype=np.int64).reshape(-1))
        if boxes.ndim != 2 or boxes.shape[1] not in (4, 7):
            raise ValueError(f"LabeledBoxes.boxes expects (N, 4) or (N, 7), got {boxes.shape}")
        if len(self.classes) != len(boxes):
            raise ValueError(f"LabeledBoxes: {len(boxes)} boxes but {len(self.classes)} classes")
        if self.probabilities is not None and len(self.probabilities) != len(boxes):
            raise ValueError(
                f"LabeledBoxes: {len(boxes)} boxes but {len(self.probabilities)} probability rows"
            )

    def __len__(self) -> int:
        return len(self.classes)

    def map_boxes(self, transform: Callable[[np.ndarray], np.ndarray]) -> LabeledBoxes:
        """The same objects with transform(boxes) as boxes (e.g. moved into another frame)."""
        return LabeledBoxes(transform(self.boxes), self.classes, self.probabilities)

    @staticmethod
    def empty(box_size: int) -> LabeledBoxes:
        """No objects; box_size 4 (2D) or 7 (3D)."""
        return LabeledBoxes(np.zeros((0, box_size)), np.zeros(0, dtype=np.int64))
