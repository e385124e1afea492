"""DetMatch pseudo-labels from teacher detections (docs/design.md section 3, steps 1-5), numpy only.

Shared by semi-supervised training and the labeling service, so both produce the same labels
from the same detections. Everything is in the un-augmented frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from detmatch.geometry import boxes_touching_image, project_boxes_to_image
from detmatch.matching import hungarian_match, matching_cost
from detmatch.matching_policy import MatchingPolicy
from detmatch.structures import Calibration, Detections


class Provenance(IntEnum):
    """Where a label came from."""

    MATCHED = 0  # a 3D and a 2D teacher detection agreed (Hungarian cost <= tau_hung)
    LIDAR_ONLY_OUTSIDE_VIEW = 1  # a confident 3D detection the camera cannot see
    LIDAR_ONLY_CONFIDENT = 2  # an unmatched 3D detection in view, above a high score


@dataclass(frozen=True)
class MatchedLabels:
    """Labels of one frame, N rows.

    boxes_3d: (N, 7) LiDAR boxes; boxes_2d: (N, 4) xyxy original pixels (matched rows: the 2D
    teacher's box; LiDAR-only rows: NaN); class_3d / class_2d: (N,) each teacher's argmax class
    (-1 where absent); score_3d / score_2d: (N,) max class probabilities (NaN where absent);
    cost: (N,) matching cost (NaN for LiDAR-only rows); provenance: (N,) Provenance values;
    index_3d / index_2d: (N,) rows of the input detections (-1 where absent).
    """

    boxes_3d: np.ndarray
    boxes_2d: np.ndarray
    class_3d: np.ndarray
    class_2d: np.ndarray
    score_3d: np.ndarray
    score_2d: np.ndarray
    cost: np.ndarray
    provenance: np.ndarray
    index_3d: np.ndarray
    index_2d: np.ndarray

    def __len__(self) -> int:
        return len(self.provenance)

    @property
    def matched(self) -> np.ndarray:
        return self.provenance == Provenance.MATCHED


def match_detections(
    detections_3d: Detections,
    detections_2d: Detections,
    calib: Calibration,
    image_size: tuple[int, int],
    policy: MatchingPolicy,
) -> MatchedLabels:
    """Hungarian-match a frame's 3D and 2D teacher detections under `policy`.

    3D boxes in the camera's view are projected (docs/design.md step 1) and matched with the 2D
    boxes; assigned pairs with cost <= policy.tau_hung become labels. 3D boxes outside the view
    whose score exceeds policy.tau_3d_outside_view are kept as LiDAR-only labels (None disables
    that fallback). In-view 3D boxes left unmatched whose score exceeds policy.tau_3d_unmatched
    are kept as LiDAR-only labels too (None: off, as in the paper): the LiDAR finds objects the
    camera misses. image_size is (W, H) of the original image.
    """
    in_view = boxes_touching_image(detections_3d.boxes, calib, image_size)
    view_rows = np.flatnonzero(in_view)
    projected = project_boxes_to_image(detections_3d.boxes[view_rows], calib, image_size)
    cost = matching_cost(
        projected,
        detections_3d.probabilities[view_rows],
        detections_2d.boxes,
        detections_2d.probabilities,
        image_size,
    )
    rows, cols = hungarian_match(cost, policy.tau_hung)
    index_3d = view_rows[rows]
    index_2d = cols
    pair_cost = cost[rows, cols]

    outside = _above(detections_3d.scores, ~in_view, policy.tau_3d_outside_view)
    unmatched_in_view = in_view.copy()
    unmatched_in_view[index_3d] = False
    confident = _above(detections_3d.scores, unmatched_in_view, policy.tau_3d_unmatched)
    n_matched = len(index_3d)
    lidar_only = np.concatenate([outside, confident])
    n_outside = len(lidar_only)
    all_3d = np.concatenate([index_3d, lidar_only]).astype(np.int64)
    absent = np.full(n_outside, -1, dtype=np.int64)
    return MatchedLabels(
        boxes_3d=detections_3d.boxes[all_3d].reshape(-1, 7),
        boxes_2d=np.concatenate(
            [detections_2d.boxes[index_2d].reshape(-1, 4), np.full((n_outside, 4), np.nan)]
        ),
        class_3d=detections_3d.probabilities[all_3d].argmax(axis=1).astype(np.int64),
        class_2d=np.concatenate(
            [detections_2d.probabilities[index_2d].argmax(axis=1).astype(np.int64), absent]
        ),
        score_3d=detections_3d.scores[all_3d].astype(np.float64),
        score_2d=np.concatenate([detections_2d.scores[index_2d], np.full(n_outside, np.nan)]),
        cost=np.concatenate([pair_cost, np.full(n_outside, np.nan)]),
        provenance=np.concatenate(
            [
                np.full(n_matched, Provenance.MATCHED, dtype=np.int64),
                np.full(len(outside), Provenance.LIDAR_ONLY_OUTSIDE_VIEW, dtype=np.int64),
                np.full(len(confident), Provenance.LIDAR_ONLY_CONFIDENT, dtype=np.int64),
            ]
        ),
        index_3d=all_3d,
        index_2d=np.concatenate([index_2d.astype(np.int64), absent]),
    )


def _above(scores: np.ndarray, rows: np.ndarray, threshold: float | None) -> np.ndarray:
    """Indices of the boolean rows whose score exceeds threshold (none for None)."""
    if threshold is None:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(rows & (scores > threshold))


def confident_detections(detections: Detections, threshold: float) -> Detections:
    """Single-modality pseudo-labels: detections whose max class probability exceeds threshold."""
    return detections[detections.scores > threshold]
