"""Running both detectors on batches and turning their outputs into KITTI result rows."""

from __future__ import annotations

import numpy as np
import torch

from detmatch.data.dataset import Batch, flip_boxes_3d
from detmatch.data.kitti import KittiObjects
from detmatch.data.results import result_objects_2d, result_objects_3d
from detmatch.models.detector2d import CenterNet2D
from detmatch.models.detector3d import PointPillars3D
from detmatch.structures import Calibration, Detections


def _to_numpy(values: tuple[torch.Tensor, ...], b: int) -> tuple[np.ndarray, ...]:
    return tuple(v[b].detach().cpu().double().numpy() for v in values)


@torch.no_grad()
def predict_batch(
    model_2d: CenterNet2D, model_3d: PointPillars3D, batch: Batch
) -> list[tuple[Detections, Detections]]:
    """Both detectors on a batch, in eval mode; detections above each detector's score
    threshold, mapped back to the un-augmented frame (original pixels; LiDAR frame)."""
    model_2d.eval()
    model_3d.eval()
    batch = batch.to(next(model_3d.parameters()).device)
    decoded_2d = model_2d.decode(*model_2d(batch.images))
    decoded_3d = model_3d.decode(
        *model_3d(
            batch.pillar_features, batch.pillar_coords, batch.pillar_counts, batch_size=len(batch)
        )
    )
    results = []
    for b, sample in enumerate(batch.samples):
        boxes, scores, classes, probabilities = _to_numpy(decoded_2d, b)
        keep = scores > model_2d.config.score_threshold
        original_boxes = sample.image_transform.invert(boxes[keep])
        detections_2d = Detections(
            original_boxes, scores[keep], classes[keep].astype(np.int64), probabilities[keep]
        )
        boxes, scores, classes, probabilities = _to_numpy(decoded_3d, b)
        keep = scores > model_3d.config.score_threshold
        boxes = flip_boxes_3d(boxes[keep]) if sample.flipped else boxes[keep]
        detections_3d = Detections(
            boxes, scores[keep], classes[keep].astype(np.int64), probabilities[keep]
        )
        results.append((detections_2d, detections_3d))
    return results


def detections_2d_to_objects(detections: Detections, class_names: tuple[str, ...]) -> KittiObjects:
    """2D detections -> KITTI result rows with KITTI's placeholder 3D fields."""
    names = [class_names[c] for c in detections.classes]
    return result_objects_2d(detections.boxes, names, detections.scores)


def detections_3d_to_objects(
    detections: Detections,
    class_names: tuple[str, ...],
    calib: Calibration,
    image_size: tuple[int, int],
) -> KittiObjects:
    """3D detections whose centre is in the camera's view -> KITTI result rows."""
    names = [class_names[c] for c in detections.classes]
    return result_objects_3d(detections.boxes, names, detections.scores, calib, image_size)
