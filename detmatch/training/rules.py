"""How a teacher-student method turns teacher detections into pseudo-labels (docs/design.md
section 3): a small strategy object per method, chosen once from the config.

- `ConfidenceThresholding`: each modality keeps its own confident detections (tau_3D, tau_2D).
- `DetMatchRule`: the 2D-3D Hungarian matching (`detmatch.pseudo_labels.match_detections`)
  keeps the objects both teachers agree on, weights the 2D pseudo-label loss x4 and hands the
  matched 2D teacher boxes to the consistency loss; the image projections of its in-view
  LiDAR-only labels are ignore regions of the 2D student instead of background.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

from detmatch.config import SemiSupervisedConfig
from detmatch.geometry import project_boxes_to_image
from detmatch.matching_policy import MatchingPolicy
from detmatch.pseudo_labels import Provenance, confident_detections, match_detections
from detmatch.structures import Calibration, Detections, LabeledBoxes


@dataclass(frozen=True)
class FramePseudoLabels:
    """One unlabeled frame's pseudo-labels, un-augmented: labels_3d LiDAR boxes, labels_2d
    original-image pixels (both with the teachers' probabilities); consistency_2d: the 2D
    teacher boxes the 3D student is pulled towards (empty for methods without it); ignore_2d:
    original-image boxes that are neither 2D labels nor background (the 2D student learns no
    background in their cells)."""

    labels_3d: LabeledBoxes
    labels_2d: LabeledBoxes
    consistency_2d: LabeledBoxes
    ignore_2d: LabeledBoxes = field(default_factory=lambda: LabeledBoxes.empty(4))


def _labels(detections: Detections) -> LabeledBoxes:
    return LabeledBoxes(detections.boxes, detections.classes, detections.probabilities)


class PseudoLabelRule(abc.ABC):
    """weight_2d: the 2D pseudo-label loss's weight relative to the 3D one; consistency: whether
    the 2D-teacher -> 3D-student consistency loss is added."""

    weight_2d: float = 1.0
    consistency: bool = False

    @abc.abstractmethod
    def frame_labels(
        self,
        detections_2d: Detections,
        detections_3d: Detections,
        calib: Calibration,
        image_size: tuple[int, int],
    ) -> FramePseudoLabels:
        """Teacher detections of one frame (un-augmented; image_size (W, H)) -> pseudo-labels."""


@dataclass(frozen=True)
class ConfidenceThresholding(PseudoLabelRule):
    tau_3d: float
    tau_2d: float

    def frame_labels(self, detections_2d, detections_3d, calib, image_size) -> FramePseudoLabels:
        return FramePseudoLabels(
            labels_3d=_labels(confident_detections(detections_3d, self.tau_3d)),
            labels_2d=_labels(confident_detections(detections_2d, self.tau_2d)),
            consistency_2d=LabeledBoxes.empty(4),
        )


def _projections(
    labels_3d: LabeledBoxes, rows: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> LabeledBoxes:
    """The image projections (original pixels) of the 3D labels in the boolean rows."""
    projected = project_boxes_to_image(labels_3d.boxes[rows], calib, image_size)
    return LabeledBoxes(projected, labels_3d.classes[rows], labels_3d.probabilities[rows])


@dataclass(frozen=True)
class DetMatchRule(PseudoLabelRule):
    """policy: which teacher detections become labels (tau_hung, the outside-view fallback, the
    in-view LiDAR-only threshold). The in-view LiDAR-only labels' image projections are 2D
    ignore regions: the camera was silent where the LiDAR is confident, so the 2D student
    learns no background there. Every other unmatched detection is background, as in the
    paper."""

    policy: MatchingPolicy
    weight_2d: float
    consistency: bool

    def frame_labels(self, detections_2d, detections_3d, calib, image_size) -> FramePseudoLabels:
        matched = match_detections(detections_3d, detections_2d, calib, image_size, self.policy)
        pairs = matched.matched
        teacher_2d = LabeledBoxes(
            matched.boxes_2d[pairs], matched.class_2d[pairs],
            detections_2d.probabilities[matched.index_2d[pairs]],
        )  # fmt: skip
        labels_3d = LabeledBoxes(
            matched.boxes_3d, matched.class_3d, detections_3d.probabilities[matched.index_3d]
        )
        lidar_only = matched.provenance == Provenance.LIDAR_ONLY_CONFIDENT
        return FramePseudoLabels(
            labels_3d=labels_3d,
            labels_2d=teacher_2d,
            consistency_2d=teacher_2d if self.consistency else LabeledBoxes.empty(4),
            ignore_2d=_projections(labels_3d, lidar_only, calib, image_size),
        )


def pseudo_label_rule(ssl: SemiSupervisedConfig) -> PseudoLabelRule:
    """The rule of `[ssl] method` (labeled-only has none)."""
    rules = {
        "confidence": lambda: ConfidenceThresholding(ssl.tau_3d, ssl.tau_2d),
        "detmatch": lambda: DetMatchRule(
            policy=MatchingPolicy.from_config(ssl),
            weight_2d=ssl.detmatch_2d_pseudo_weight,
            consistency=ssl.consistency_class or ssl.consistency_box,
        ),
    }
    if ssl.method not in rules:  # labeled-only and its control learn from no pseudo-labels
        raise ValueError(f"[ssl] method {ssl.method!r} has no pseudo-label rule")
    return rules[ssl.method]()
