"""How a teacher-student method turns teacher detections into pseudo-labels (docs/design.md
section 3): a small strategy object per method, chosen once from the config.

- `ConfidenceThresholding`: each modality keeps its own confident detections (tau_3D, tau_2D).
- `DetMatchRule`: the 2D-3D Hungarian matching (`detmatch.pseudo_labels.match_detections`)
  keeps the objects both teachers agree on, weights the 2D pseudo-label loss x4 and hands the
  matched 2D teacher boxes to the consistency loss; optionally, each teacher's confident
  unmatched detections become ignore regions instead of background.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

from detmatch.config import SemiSupervisedConfig
from detmatch.geometry import project_boxes_to_image
from detmatch.pseudo_labels import Provenance, confident_detections, match_detections
from detmatch.structures import Calibration, Detections, LabeledBoxes


@dataclass(frozen=True)
class FramePseudoLabels:
    """One unlabeled frame's pseudo-labels, un-augmented: labels_3d LiDAR boxes, labels_2d
    original-image pixels (both with the teachers' probabilities); consistency_2d: the 2D
    teacher boxes the 3D student is pulled towards (empty for methods without it); ignore_3d /
    ignore_2d: detections that are neither labels nor background (the students learn no
    background around them)."""

    labels_3d: LabeledBoxes
    labels_2d: LabeledBoxes
    consistency_2d: LabeledBoxes
    ignore_3d: LabeledBoxes = field(default_factory=lambda: LabeledBoxes.empty(7))
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


def _unmatched(detections: Detections, used: np.ndarray, threshold: float) -> LabeledBoxes:
    """Detections outside the rows `used` whose max class probability exceeds threshold."""
    rest = np.ones(len(detections), dtype=bool)
    rest[used] = False
    return _labels(detections[rest & (detections.scores > threshold)])


def _with_projections(
    ignore_2d: LabeledBoxes,
    labels_3d: LabeledBoxes,
    rows: np.ndarray,
    calib: Calibration,
    image_size: tuple[int, int],
) -> LabeledBoxes:
    """The 2D ignore regions plus the image projections of the 3D labels in the boolean rows."""
    projected = project_boxes_to_image(labels_3d.boxes[rows], calib, image_size)
    return LabeledBoxes(
        np.concatenate([ignore_2d.boxes, projected]),
        np.concatenate([ignore_2d.classes, labels_3d.classes[rows]]),
        np.concatenate([ignore_2d.probabilities, labels_3d.probabilities[rows]]),
    )


@dataclass(frozen=True)
class DetMatchRule(PseudoLabelRule):
    """tau_3d_outside_view: the confidence fallback for 3D boxes the camera cannot see (None:
    off); tau_3d_unmatched: the one for in-view 3D boxes the 2D teacher did not confirm (None:
    off); ignore_score_3d / ignore_score_2d: that teacher's unmatched detections above it become
    ignore regions (1.0: none, every unmatched detection is background as in the paper);
    lidar_only_ignore_2d: the in-view LiDAR-only labels' image projections become 2D ignore
    regions too (the camera was silent where the LiDAR is confident)."""

    tau_hung: float
    tau_3d_outside_view: float | None
    weight_2d: float
    consistency: bool
    tau_3d_unmatched: float | None = None
    ignore_score_3d: float = 1.0
    ignore_score_2d: float = 1.0
    lidar_only_ignore_2d: bool = False

    def frame_labels(self, detections_2d, detections_3d, calib, image_size) -> FramePseudoLabels:
        matched = match_detections(
            detections_3d, detections_2d, calib, image_size, self.tau_hung,
            self.tau_3d_outside_view, self.tau_3d_unmatched,
        )  # fmt: skip
        pairs = matched.matched
        rows_2d = matched.index_2d[pairs]
        teacher_2d = LabeledBoxes(
            matched.boxes_2d[pairs], matched.class_2d[pairs],
            detections_2d.probabilities[rows_2d],
        )  # fmt: skip
        labels_3d = LabeledBoxes(
            matched.boxes_3d, matched.class_3d, detections_3d.probabilities[matched.index_3d]
        )
        ignore_2d = _unmatched(detections_2d, rows_2d, self.ignore_score_2d)
        if self.lidar_only_ignore_2d:
            ignore_2d = _with_projections(
                ignore_2d, labels_3d, matched.provenance == Provenance.LIDAR_ONLY_CONFIDENT,
                calib, image_size,
            )  # fmt: skip
        return FramePseudoLabels(
            labels_3d=labels_3d,
            labels_2d=teacher_2d,
            consistency_2d=teacher_2d if self.consistency else LabeledBoxes.empty(4),
            ignore_3d=_unmatched(detections_3d, matched.index_3d, self.ignore_score_3d),
            ignore_2d=ignore_2d,
        )


def pseudo_label_rule(ssl: SemiSupervisedConfig) -> PseudoLabelRule:
    """The rule of `[ssl] method` (labeled-only has none)."""
    rules = {
        "confidence": lambda: ConfidenceThresholding(ssl.tau_3d, ssl.tau_2d),
        "detmatch": lambda: DetMatchRule(
            tau_hung=ssl.tau_hung,
            tau_3d_outside_view=ssl.tau_3d if ssl.fov_fallback else None,
            weight_2d=ssl.detmatch_2d_pseudo_weight,
            consistency=ssl.consistency_class or ssl.consistency_box,
            tau_3d_unmatched=ssl.unmatched_3d_threshold,
            ignore_score_3d=ssl.ignore_unmatched_score_3d,
            ignore_score_2d=ssl.ignore_unmatched_score_2d,
            lidar_only_ignore_2d=ssl.lidar_only_ignore_2d,
        ),
    }
    if ssl.method not in rules:  # labeled-only and its control learn from no pseudo-labels
        raise ValueError(f"[ssl] method {ssl.method!r} has no pseudo-label rule")
    return rules[ssl.method]()
