"""KITTI result rows from detections or labels (numpy only: training and serving share it)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from detmatch.data.kitti import (
    PLACEHOLDER_DIMENSIONS,
    PLACEHOLDER_LOCATION,
    PLACEHOLDER_ROTATION,
    KittiObjects,
)
from detmatch.geometry import (
    box_centres_in_image,
    lidar_to_kitti_camera_boxes,
    limit_period,
    project_boxes_to_image,
)
from detmatch.structures import Calibration


def result_objects_3d(
    boxes: np.ndarray,
    names: Sequence[str],
    scores: np.ndarray,
    calib: Calibration,
    image_size: tuple[int, int],
) -> KittiObjects:
    """(N, 7) LiDAR boxes in the camera's view -> KITTI result rows (camera-frame box, projected
    2D box, alpha). Boxes whose centre is outside the image are dropped: KITTI labels only the
    camera's field of view."""
    keep = box_centres_in_image(boxes, calib, image_size)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)[keep]
    location, dimensions, rotation_y = lidar_to_kitti_camera_boxes(boxes, calib)
    n = len(boxes)
    return KittiObjects(
        names=np.asarray(names, dtype=object).reshape(-1)[keep],
        truncated=np.full(n, -1.0),
        occluded=np.full(n, -1, dtype=np.int64),
        alpha=limit_period(rotation_y - np.arctan2(location[:, 0], location[:, 2])),
        bbox=project_boxes_to_image(boxes, calib, image_size),
        dimensions=dimensions,
        location=location,
        rotation_y=rotation_y,
        score=np.asarray(scores, dtype=np.float64)[keep],
    )


def result_objects_2d(boxes: np.ndarray, names: Sequence[str], scores: np.ndarray) -> KittiObjects:
    """(N, 4) xyxy boxes -> KITTI result rows with KITTI's placeholder 3D fields."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    n = len(boxes)
    return KittiObjects(
        names=np.asarray(names, dtype=object).reshape(-1),
        truncated=np.full(n, -1.0),
        occluded=np.full(n, -1, dtype=np.int64),
        alpha=np.full(n, PLACEHOLDER_ROTATION),
        bbox=boxes,
        dimensions=np.tile(PLACEHOLDER_DIMENSIONS, (n, 1)),
        location=np.tile(PLACEHOLDER_LOCATION, (n, 1)),
        rotation_y=np.full(n, PLACEHOLDER_ROTATION),
        score=np.asarray(scores, dtype=np.float64),
    )
