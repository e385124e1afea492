"""One serialiser for a frame's labels: the gRPC response, the label store and `detmatch label`
all read `label_records`, and the KITTI files come from the same labels.

Torch-free and gRPC-free: the servicer turns records into protos, the store and the batch
labeler into JSON and KITTI result rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from detmatch.data.kitti import KittiObjects
from detmatch.data.results import result_objects_2d, result_objects_3d
from detmatch.pseudo_labels import Provenance
from detmatch.structures import Calibration
from serving.labeler import FrameLabels

PROVENANCE_NAMES = {
    Provenance.MATCHED: "matched",
    Provenance.LIDAR_ONLY_OUTSIDE_VIEW: "lidar_only_outside_view",
    Provenance.LIDAR_ONLY_CONFIDENT: "lidar_only_confident",
}
BOX_3D_FIELDS = ("x", "y", "z", "l", "w", "h", "yaw")
BOX_2D_FIELDS = ("x1", "y1", "x2", "y2")


@dataclass(frozen=True)
class LabelRecord:
    """One label as every consumer sees it. box_3d: LiDAR frame x y z l w h yaw (gravity
    centre, metres, radians); box_2d: x1 y1 x2 y2 original-image pixels. The 2D fields and the
    cost are None for LiDAR-only labels."""

    provenance: Provenance
    class_3d: str
    box_3d: tuple[float, ...]
    score_3d: float
    class_2d: str | None
    box_2d: tuple[float, ...] | None
    score_2d: float | None
    cost: float | None

    @property
    def provenance_name(self) -> str:
        return PROVENANCE_NAMES[self.provenance]

    def to_json(self) -> dict[str, Any]:
        """JSON-ready, numbers rounded to 6 decimals."""
        return {
            "provenance": self.provenance_name,
            "class_3d": self.class_3d,
            "class_2d": self.class_2d,
            "box_3d": [round(v, 6) for v in self.box_3d],
            "box_2d": None if self.box_2d is None else [round(v, 6) for v in self.box_2d],
            "score_3d": round(self.score_3d, 6),
            "score_2d": None if self.score_2d is None else round(self.score_2d, 6),
            "cost": None if self.cost is None else round(self.cost, 6),
        }


def label_records(result: FrameLabels) -> list[LabelRecord]:
    """The labels of one frame, in the labeler's order."""
    labels, classes = result.labels, result.classes
    records = []
    for i in range(len(labels)):
        matched = bool(labels.matched[i])
        records.append(
            LabelRecord(
                provenance=Provenance(int(labels.provenance[i])),
                class_3d=classes[labels.class_3d[i]],
                box_3d=tuple(float(v) for v in labels.boxes_3d[i]),
                score_3d=float(labels.score_3d[i]),
                class_2d=classes[labels.class_2d[i]] if matched else None,
                box_2d=tuple(float(v) for v in labels.boxes_2d[i]) if matched else None,
                score_2d=_finite(labels.score_2d[i]),
                cost=_finite(labels.cost[i]),
            )
        )
    return records


def labels_to_json(frame_id: str, result: FrameLabels) -> dict[str, Any]:
    """Every label of a frame, JSON-ready (absent fields are null)."""
    return {
        "frame_id": frame_id,
        "model_version": result.model_version,
        "image_size": list(result.image_size),
        "thresholds": result.thresholds,
        "box_3d": "LiDAR frame x y z l w h yaw, gravity centre",
        "box_2d": "x1 y1 x2 y2 pixels",
        "labels": [record.to_json() for record in label_records(result)],
        # what the camera saw and no label holds: the review's disagreement ranking reads it
        "unmatched_2d": unmatched_2d(result),
    }


def unmatched_2d(result: FrameLabels) -> list[dict[str, Any]]:
    """The 2D detections (above the score threshold) that no label took, best first."""
    detections = result.detections_2d
    taken = set(int(i) for i in result.labels.index_2d if i >= 0)
    rows = [i for i in np.argsort(-detections.scores, kind="stable") if int(i) not in taken]
    return [
        {"class_2d": result.classes[int(detections.classes[i])],
         "box_2d": [round(float(v), 2) for v in detections.boxes[i]],
         "score_2d": round(float(detections.scores[i]), 4)}
        for i in rows
    ]  # fmt: skip


def labels_to_objects_3d(result: FrameLabels, calib: Calibration) -> KittiObjects:
    """Labels whose 3D box centre projects into the image -> KITTI result rows (camera-frame
    box, projected 2D box, alpha; the 3D class and score)."""
    labels = result.labels
    names = [result.classes[c] for c in labels.class_3d]
    return result_objects_3d(labels.boxes_3d, names, labels.score_3d, calib, result.image_size)


def labels_to_objects_2d(result: FrameLabels) -> KittiObjects:
    """Matched labels' 2D boxes -> KITTI result rows with KITTI's placeholder 3D fields."""
    labels = result.labels
    keep = labels.matched
    names = [result.classes[c] for c in labels.class_2d[keep]]
    return result_objects_2d(labels.boxes_2d[keep], names, labels.score_2d[keep])


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None
