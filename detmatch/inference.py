"""Running both detectors on batches and turning their outputs into KITTI result rows."""

from __future__ import annotations

import numpy as np
import torch

from detmatch.data.dataset import Batch, flip_boxes_3d
from detmatch.data.kitti import (
    PLACEHOLDER_DIMENSIONS,
    PLACEHOLDER_LOCATION,
    PLACEHOLDER_ROTATION,
    KittiObjects,
)
from detmatch.geometry import (
    lidar_to_kitti_camera_boxes,
    limit_period,
    points_in_image,
    project_boxes_to_image,
)
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


def in_camera_view(
    boxes: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> np.ndarray:
    """(N, 7) LiDAR boxes -> (N,) bool: the box centre projects into the image, in front."""
    return points_in_image(np.asarray(boxes).reshape(-1, 7)[:, :3], calib, image_size)


def detections_2d_to_objects(detections: Detections, class_names: tuple[str, ...]) -> KittiObjects:
    """2D detections -> KITTI result rows with KITTI's placeholder 3D fields."""
    n = len(detections)
    return KittiObjects(
        names=np.array([class_names[c] for c in detections.classes], dtype=object),
        truncated=np.full(n, -1.0),
        occluded=np.full(n, -1, dtype=np.int64),
        alpha=np.full(n, PLACEHOLDER_ROTATION),
        bbox=detections.boxes,
        dimensions=np.tile(PLACEHOLDER_DIMENSIONS, (n, 1)),
        location=np.tile(PLACEHOLDER_LOCATION, (n, 1)),
        rotation_y=np.full(n, PLACEHOLDER_ROTATION),
        score=detections.scores,
    )


def detections_3d_to_objects(
    detections: Detections,
    class_names: tuple[str, ...],
    calib: Calibration,
    image_size: tuple[int, int],
) -> KittiObjects:
    """3D detections in the camera's view -> KITTI result rows (camera-frame box, projected 2D
    box, alpha). Boxes whose centre is outside the image are dropped: KITTI labels only the
    camera's field of view."""
    detections = detections[in_camera_view(detections.boxes, calib, image_size)]
    location, dimensions, rotation_y = lidar_to_kitti_camera_boxes(detections.boxes, calib)
    alpha = limit_period(rotation_y - np.arctan2(location[:, 0], location[:, 2]))
    n = len(detections)
    return KittiObjects(
        names=np.array([class_names[c] for c in detections.classes], dtype=object),
        truncated=np.full(n, -1.0),
        occluded=np.full(n, -1, dtype=np.int64),
        alpha=alpha,
        bbox=project_boxes_to_image(detections.boxes, calib, image_size),
        dimensions=dimensions,
        location=location,
        rotation_y=rotation_y,
        score=detections.scores,
    )
