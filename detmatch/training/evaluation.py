"""Evaluating both detectors on a labeled split with the project's KITTI evaluator."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from detmatch.data.dataset import FrameDataset, collate
from detmatch.data.kitti import objects_to_labels
from detmatch.eval.kitti import evaluate
from detmatch.geometry import nearest_in_bev
from detmatch.inference import detections_2d_to_objects, detections_3d_to_objects, predict_batch
from detmatch.models.contract import Detector2D, Detector3D
from detmatch.structures import Detections

MODERATE = 1


def headline(results: dict[str, Any], metric: str, classes: tuple[str, ...]) -> dict[str, float]:
    """Moderate R40 AP per class and their mean ("mAP") for one metric ("bbox", "bev", "3d")."""
    per_class = {c: float(results[c]["R40"][metric][MODERATE]) for c in classes}
    per_class["mAP"] = sum(per_class.values()) / len(classes)
    return per_class


def evaluate_detectors(
    model_2d: Detector2D,
    model_3d: Detector3D,
    dataset: FrameDataset,
    classes: tuple[str, ...],
    batch_size: int = 4,
    num_workers: int = 0,
) -> dict[str, Any]:
    """Predict every frame of dataset (no augmentation) and score both modalities.

    Returns {"2d": moderate R40 bbox AP per class + mAP, "3d": ... 3D AP, "bev": ... BEV AP,
    "box_errors": box_errors of the 3D detections, "full_2d": evaluator output, "full_3d":
    evaluator output}.
    """
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=batch_size, collate_fn=collate, num_workers=num_workers
    )
    ground_truth, objects_2d, objects_3d = [], [], []
    errors: dict[str, list[np.ndarray]] = {c: [] for c in classes}
    for batch in loader:
        for sample, (detections_2d, detections_3d) in zip(
            batch.samples, predict_batch(model_2d, model_3d, batch), strict=True
        ):
            objects = dataset.kitti.read_objects(sample.frame_id)
            ground_truth.append(objects)
            labels = objects_to_labels(objects, sample.calib)
            for class_id, name in enumerate(classes):
                errors[name].append(
                    signed_box_errors(
                        detections_3d[detections_3d.classes == class_id],
                        labels.boxes_3d.data[labels.names == name],
                    )
                )
            objects_2d.append(detections_2d_to_objects(detections_2d, classes))
            objects_3d.append(
                detections_3d_to_objects(
                    detections_3d, classes, sample.calib, sample.image_transform.original_size
                )
            )
    full_2d = evaluate(ground_truth, objects_2d, classes)
    full_3d = evaluate(ground_truth, objects_3d, classes)
    return {
        "2d": headline(full_2d, "bbox", classes),
        "3d": headline(full_3d, "3d", classes),
        "bev": headline(full_3d, "bev", classes),
        "box_errors": {name: summarise_errors(rows) for name, rows in errors.items()},
        "full_2d": full_2d,
        "full_3d": full_3d,
    }


# A confident detection's signed error is measured against the nearest ground-truth box of
# its class within this distance (metres, bird's-eye view).
ERROR_MATCH_DISTANCE = 1.5
ERROR_MIN_SCORE = 0.3


def signed_box_errors(detections: Detections, boxes: np.ndarray) -> np.ndarray:
    """(M, 4) predicted minus true length, width, height and z of each confident detection
    (score > ERROR_MIN_SCORE) whose nearest ground-truth box (N, 7) of the class is within
    ERROR_MATCH_DISTANCE in bird's-eye view. LiDAR frame, metres."""
    confident = detections[detections.scores > ERROR_MIN_SCORE]
    if len(confident) == 0 or len(boxes) == 0:
        return np.zeros((0, 4))
    nearest = nearest_in_bev(confident.boxes, boxes, ERROR_MATCH_DISTANCE)
    close = nearest >= 0
    predicted, true = confident.boxes[close], boxes[nearest[close]]
    columns = [3, 4, 5, 2]  # l, w, h, z
    return predicted[:, columns] - true[:, columns]


def summarise_errors(rows: list[np.ndarray]) -> dict[str, float]:
    """Mean signed errors (and their count) of one class over a data set."""
    errors = np.concatenate(rows) if rows else np.zeros((0, 4))
    means = [float(v) for v in errors.mean(axis=0)] if len(errors) else [None] * 4
    return {"count": int(len(errors)), **dict(zip(("l", "w", "h", "z"), means, strict=True))}
