"""Evaluating both detectors on a labeled split with the project's KITTI evaluator."""

from __future__ import annotations

from typing import Any

import torch

from detmatch.data.dataset import FrameDataset, collate
from detmatch.eval.kitti import evaluate
from detmatch.inference import detections_2d_to_objects, detections_3d_to_objects, predict_batch
from detmatch.models.contract import Detector2D, Detector3D

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
    "full_2d": evaluator output, "full_3d": evaluator output}.
    """
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=batch_size, collate_fn=collate, num_workers=num_workers
    )
    ground_truth, objects_2d, objects_3d = [], [], []
    for batch in loader:
        for sample, (detections_2d, detections_3d) in zip(
            batch.samples, predict_batch(model_2d, model_3d, batch), strict=True
        ):
            ground_truth.append(dataset.kitti.read_objects(sample.frame_id))
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
        "full_2d": full_2d,
        "full_3d": full_3d,
    }
