"""The contract between a detector and the DetMatch method, one per modality.

Training, teacher-student learning, the consistency loss, prediction and ONNX export use a
detector only through these two base classes (`detmatch.models.build` maps config names to
classes). A detector is an `nn.Module` that implements:

- `forward(...) -> tuple[Tensor, ...]`: tensors in, raw head outputs out, each with the batch as
  its first dimension (so a batch of labeled + unlabeled frames can be split); this and
  `decode` are what the exported graph runs.
- `decode(outputs) -> (boxes, scores, classes, probabilities)`: the top-k detections of every
  frame, tensors (B, K, 4 or 7), (B, K), (B, K), (B, K, C), in the detector's input frame;
  traceable for ONNX.
- `build_targets(labels, ...) -> targets`: one frame's typed training targets (a dataclass
  of the detector's own) from `LabeledBoxes`, ground truth or pseudo-labels alike.
- `loss(outputs, targets, box_regression=True) -> dict[str, Tensor]`: named, weighted loss
  terms; without box_regression only the classification terms (the 2D pseudo-label loss).
- 3D only: `consistency_candidates(outputs) -> ConsistencyCandidates`, the differentiable
  decode the 2D-teacher -> 3D-student consistency loss pulls on, and the attribute
  `consistency_gradient`, which says where that loss's box gradient goes. A detector with a
  second stage should return the refined boxes there, so the dense box regression is not
  pulled by the 2D teacher (the authors' PV-RCNN trains only its RoI head this way;
  `PointPillars3D` with `[detector3d] refine` does the same).

`detect(outputs)` turns decoded outputs into per-frame `Detections` above the detector's score
threshold, still in the input frame; `detmatch.inference` maps them back to the un-augmented
frame.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from detmatch.models.pillars import PillarGrid, Pillars
from detmatch.structures import Detections, LabeledBoxes

Decoded = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def split_outputs(
    outputs: Sequence[torch.Tensor], n: int
) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
    """Raw outputs of a batch -> (the first n frames', the rest's)."""
    return tuple(o[:n] for o in outputs), tuple(o[n:] for o in outputs)


def _detections(decoded: Decoded, threshold: float) -> list[Detections]:
    """Decoded tensors -> per-frame Detections (float64) with max probability > threshold."""
    boxes, scores, classes, probabilities = (v.detach().cpu().double().numpy() for v in decoded)
    frames = []
    for b in range(len(scores)):
        keep = scores[b] > threshold
        frames.append(
            Detections(
                boxes[b][keep],
                scores[b][keep],
                classes[b][keep].astype(np.int64),
                probabilities[b][keep],
            )
        )
    return frames


class Detector(nn.Module, abc.ABC):
    """What both modalities' detectors share: raw outputs -> decoded boxes, a loss against
    built targets, and per-frame detections. Boxes are in the detector's input coordinates."""

    num_classes: int
    score_threshold: float
    # Names of forward's outputs, in order (the exported graph's raw outputs): a class or an
    # instance attribute.
    output_names: tuple[str, ...]

    @abc.abstractmethod
    def decode(self, outputs: Sequence[torch.Tensor]) -> Decoded: ...

    @abc.abstractmethod
    def loss(
        self,
        outputs: Sequence[torch.Tensor],
        targets: Sequence[Any],
        box_regression: bool = True,
    ) -> dict[str, torch.Tensor]:
        """Named, weighted loss terms; without box_regression only the classification ones."""

    def detect(self, outputs: Sequence[torch.Tensor]) -> list[Detections]:
        """Per-frame detections above the score threshold, boxes in the input's coordinates."""
        return _detections(self.decode(outputs), self.score_threshold)


class Detector2D(Detector):
    """A camera detector. Images are (B, 3, H, W) float RGB in [0, 255] (H, W multiples of
    the detector's stride); boxes are xyxy pixels of that input."""

    @abc.abstractmethod
    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]: ...

    @abc.abstractmethod
    def build_targets(
        self,
        labels: LabeledBoxes,
        input_size: tuple[int, int],
        ignore: np.ndarray | None = None,
    ) -> Any:
        """labels: boxes in input pixels; input_size: (W, H) of the network input; ignore:
        (M, 4) boxes in input pixels where background is not learned (uncertain objects)."""


class LabelledArea(Protocol):
    """Where a frame's 3D labels are complete, so background may be learned (KITTI-style labels
    cover only the camera's view; `detmatch.data.dataset.CameraView` implements it)."""

    def contains_bev(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) x, y metres in the detector's input frame -> (N,) bool."""
        ...


@dataclass(frozen=True)
class ConsistencyCandidates:
    """The 3D student's top-k boxes of each frame for the consistency loss: boxes (B, K, 7)
    and class logits (B, K, C) carry gradients; scores (B, K) and probabilities (B, K, C) are
    detached (they only select and match)."""

    boxes: torch.Tensor
    logits: torch.Tensor
    scores: torch.Tensor
    probabilities: torch.Tensor


class Detector3D(Detector):
    """A LiDAR detector on pillars (`detmatch.models.pillars`); boxes are LiDAR-frame
    x, y, z, l, w, h, yaw in the input's (augmented) frame."""

    grid: PillarGrid
    # Where the consistency loss's box gradient goes, in words (logged and documented).
    consistency_gradient: str

    @abc.abstractmethod
    def forward(
        self,
        features: torch.Tensor,
        coords: torch.Tensor,
        counts: torch.Tensor,
        batch_size: int = 1,
    ) -> tuple[torch.Tensor, ...]:
        """features (P, M, 9), coords (P, 3) (frame, iy, ix), counts (P,): a batch's pillars."""

    @abc.abstractmethod
    def build_targets(
        self,
        labels: LabeledBoxes,
        view: LabelledArea | None = None,
        ignore: np.ndarray | None = None,
    ) -> Any:
        """labels: boxes in the input frame; view: where background may be learned (None:
        everywhere); ignore: (M, 7) boxes in the input frame around which background is not
        learned (uncertain objects)."""

    @abc.abstractmethod
    def consistency_candidates(self, outputs: Sequence[torch.Tensor]) -> ConsistencyCandidates: ...


def forward_pillars(module: nn.Module, pillars: Pillars) -> tuple[torch.Tensor, ...]:
    """A 3D detector's (or its DDP wrapper's) raw outputs for a batch of pillars."""
    return module(pillars.features, pillars.coords, pillars.counts, batch_size=pillars.batch_size)
