"""Pure box geometry on numpy arrays: corners, frame transforms, projection, IoU.

No torch here: the labeling service reuses these functions. Conventions (docs/design.md section 2):
3D boxes are LiDAR-frame (N, 7) x, y, z, l, w, h, yaw with a gravity centre; 2D boxes are
(N, 4) x1, y1, x2, y2 pixels.
"""

from __future__ import annotations

import numpy as np

from detmatch.structures import Calibration

# Unit box corners, bottom face then top face; each face counter-clockwise seen from above.
_UNIT_CORNERS = 0.5 * np.array(
    [
        [1, -1, -1],
        [1, 1, -1],
        [-1, 1, -1],
        [-1, -1, -1],
        [1, -1, 1],
        [1, 1, 1],
        [-1, 1, 1],
        [-1, -1, 1],
    ],
    dtype=np.float64,
)

PROJECTION_MIN_DEPTH = 1e-5


def rotation_z(yaw: np.ndarray) -> np.ndarray:
    """(N,) angles -> (N, 3, 3) rotations about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    zeros, ones = np.zeros_like(c), np.ones_like(c)
    return np.stack(
        [
            np.stack([c, -s, zeros], -1),
            np.stack([s, c, zeros], -1),
            np.stack([zeros, zeros, ones], -1),
        ],
        axis=-2,
    )


def box3d_corners(boxes: np.ndarray) -> np.ndarray:
    """(N, 7) boxes -> (N, 8, 3) corners in the boxes' frame; bottom face first."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    local = _UNIT_CORNERS[None] * boxes[:, None, 3:6]
    return np.einsum("nij,nkj->nki", rotation_z(boxes[:, 6]), local) + boxes[:, None, 0:3]


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """(N, 7) boxes -> (N, 4, 2) bird's-eye-view corners (x, y), counter-clockwise."""
    return box3d_corners(boxes)[:, :4, :2]


def _homogeneous(points: np.ndarray) -> np.ndarray:
    return np.concatenate([points, np.ones((*points.shape[:-1], 1))], axis=-1)


def lidar_to_rect(points: np.ndarray, calib: Calibration) -> np.ndarray:
    """(..., 3) LiDAR points -> (..., 3) rectified camera coordinates."""
    return _homogeneous(np.asarray(points, dtype=np.float64)) @ calib.lidar_to_rect[:3].T


def rect_to_lidar(points: np.ndarray, calib: Calibration) -> np.ndarray:
    """(..., 3) rectified camera points -> (..., 3) LiDAR coordinates (exact inverse)."""
    inverse = np.linalg.inv(calib.lidar_to_rect)
    return _homogeneous(np.asarray(points, dtype=np.float64)) @ inverse[:3].T


def rect_to_image(points: np.ndarray, calib: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) rectified camera points -> ((..., 2) pixels u, v; (...,) depth).

    Depth is the projective third coordinate, clamped to >= 1e-5 before the division.
    """
    projected = _homogeneous(np.asarray(points, dtype=np.float64)) @ calib.P2.T
    depth = np.maximum(projected[..., 2], PROJECTION_MIN_DEPTH)
    return projected[..., :2] / depth[..., None], projected[..., 2]


def lidar_to_image(points: np.ndarray, calib: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) LiDAR points -> ((..., 2) pixels u, v; (...,) depth), through P2 . R0 . Tr."""
    projected = _homogeneous(np.asarray(points, dtype=np.float64)) @ calib.lidar_to_image.T
    depth = np.maximum(projected[..., 2], PROJECTION_MIN_DEPTH)
    return projected[..., :2] / depth[..., None], projected[..., 2]


def project_boxes_to_image(
    boxes: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> np.ndarray:
    """(N, 7) LiDAR boxes -> (N, 4) image boxes, exactly as docs/design.md section 3 step 1.

    The 8 corners go through lidar -> image, depth is clamped to >= 1e-5, u = x/d, v = y/d;
    the box is (min u, min v, max u, max v) clipped to [0, W - 1] x [0, H - 1] (OpenPCDet's
    convention; KITTI's own 2D labels stop at W - 1). image_size is (W, H).
    """
    width, height = image_size
    uv, _ = lidar_to_image(box3d_corners(boxes), calib)
    xyxy = np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)
    xyxy[:, 0::2] = np.clip(xyxy[:, 0::2], 0, width - 1)
    xyxy[:, 1::2] = np.clip(xyxy[:, 1::2], 0, height - 1)
    return xyxy


# ---------------------------------------------------------------------------------------------
# "Inside the camera's view": one function per notion, each right for its use.

# The consistency loss keeps a projected 3D box when at least this many of its corners fall in
# the image and its corners' mean depth is at least this many metres (the authors' values).
CONSISTENCY_MIN_CORNERS = 3
CONSISTENCY_MIN_MEAN_DEPTH = 0.5
# Height (LiDAR z, metres: about the road) at which bird's-eye-view cells are tested.
BEV_VIEW_TEST_HEIGHT = -0.8


def points_in_image(
    points: np.ndarray, calib: Calibration, image_size: tuple[int, int], min_depth: float = 0.0
) -> np.ndarray:
    """(N, 3) LiDAR points -> (N,) bool: deeper than min_depth in front of the camera and
    projecting inside the image (W, H). The building block of the notions below; the frame
    picture draws the points it passes (with min_depth 1 m)."""
    uv, depth = lidar_to_image(points, calib)
    width, height = image_size
    return (
        (depth > min_depth)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] < width)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] < height)
    )


def box_centres_in_image(
    boxes: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> np.ndarray:
    """(N, 7) LiDAR boxes -> (N,) bool: the box's centre projects into the image.

    Used for KITTI result files (`detmatch.data.results`): KITTI labels objects in the camera's
    field of view, and a box reported as a result row must have a place in the image.
    """
    return points_in_image(np.asarray(boxes, dtype=np.float64).reshape(-1, 7)[:, :3], calib,
                           image_size)  # fmt: skip


def boxes_touching_image(
    boxes: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> np.ndarray:
    """(N, 7) LiDAR boxes -> (N,) bool: at least one corner in front of the camera and inside
    the image.

    Used by the 2D-3D matching (`detmatch.pseudo_labels.match_detections`): a box the camera
    sees even partly is a matching candidate (truncated objects included); the others can only
    become LiDAR-only labels by the confidence fallback.
    """
    corners = box3d_corners(np.asarray(boxes, dtype=np.float64).reshape(-1, 7))
    inside = points_in_image(corners.reshape(-1, 3), calib, image_size)
    return inside.reshape(len(corners), 8).any(axis=1)


def bev_cells_in_camera_view(
    xy: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> np.ndarray:
    """(N, 2) LiDAR x, y -> (N,) bool: the ground point at BEV_VIEW_TEST_HEIGHT projects in
    front of the camera between the image's left and right edges (rows are not tested).

    Used for the 3D detector's training targets: KITTI-style labels exist only in the camera's
    horizontal field of view, so background is learned only in cells that pass (a cell far
    away is in view although its ground point projects below the horizon rows, and vice versa).
    """
    points = np.column_stack([xy, np.full(len(xy), BEV_VIEW_TEST_HEIGHT)])
    uv, depth = lidar_to_image(points, calib)
    return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < image_size[0])


def boxes_usable_for_consistency(
    boxes: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> np.ndarray:
    """(N, 7) LiDAR boxes -> (N,) bool: at least CONSISTENCY_MIN_CORNERS corners in the image
    and a mean corner depth of at least CONSISTENCY_MIN_MEAN_DEPTH metres.

    Used by the 2D-teacher -> 3D-student consistency loss, whose differentiable torch twin is
    `detmatch.training.consistency.project_boxes_torch`: a projection from fewer corners, or
    of a box around the camera, is too distorted to compare with a 2D box.
    """
    corners = box3d_corners(np.asarray(boxes, dtype=np.float64).reshape(-1, 7))
    inside = points_in_image(corners.reshape(-1, 3), calib, image_size).reshape(-1, 8)
    _, depth = lidar_to_image(corners.reshape(-1, 3), calib)
    return (inside.sum(axis=1) >= CONSISTENCY_MIN_CORNERS) & (
        depth.reshape(-1, 8).mean(axis=1) >= CONSISTENCY_MIN_MEAN_DEPTH
    )


# ---------------------------------------------------------------------------------------------
# KITTI camera-frame boxes <-> LiDAR boxes


def kitti_camera_to_lidar_boxes(
    location: np.ndarray, dimensions_hwl: np.ndarray, rotation_y: np.ndarray, calib: Calibration
) -> np.ndarray:
    """KITTI label fields -> (N, 7) LiDAR boxes.

    location: (N, 3) rectified-camera bottom centre; dimensions_hwl: (N, 3) h, w, l;
    rotation_y: (N,) about the camera's y axis (down).
    """
    location = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    h, w, l = np.asarray(dimensions_hwl, dtype=np.float64).reshape(-1, 3).T
    centre = rect_to_lidar(location, calib)
    centre[:, 2] += h / 2
    yaw = -(np.asarray(rotation_y, dtype=np.float64).reshape(-1) + np.pi / 2)
    return np.stack([*centre.T, l, w, h, limit_period(yaw)], axis=1)


def lidar_to_kitti_camera_boxes(
    boxes: np.ndarray, calib: Calibration
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 7) LiDAR boxes -> ((N, 3) camera bottom centre, (N, 3) h w l, (N,) rotation_y)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    bottom = boxes[:, 0:3].copy()
    bottom[:, 2] -= boxes[:, 5] / 2
    location = lidar_to_rect(bottom, calib)
    dimensions = boxes[:, [5, 4, 3]]
    rotation_y = limit_period(-boxes[:, 6] - np.pi / 2)
    return location, dimensions, rotation_y


def upright_boxes_from_camera(
    location: np.ndarray, dimensions_hwl: np.ndarray, rotation_y: np.ndarray
) -> np.ndarray:
    """KITTI camera-frame label fields -> (N, 7) boxes in the camera's 'upright' frame.

    The upright frame is a pure rotation of the rectified camera frame (x = z_cam, y = -x_cam,
    z = -y_cam), laid out like the LiDAR frame. IoUs computed there equal IoUs in the camera
    frame, so evaluation needs no calibration.
    """
    location = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    h, w, l = np.asarray(dimensions_hwl, dtype=np.float64).reshape(-1, 3).T
    centre = np.stack([location[:, 2], -location[:, 0], -location[:, 1] + h / 2], axis=1)
    yaw = -(np.asarray(rotation_y, dtype=np.float64).reshape(-1) + np.pi / 2)
    return np.concatenate([centre, np.stack([l, w, h, yaw], axis=1)], axis=1)


def limit_period(angle: np.ndarray, offset: float = 0.5, period: float = 2 * np.pi) -> np.ndarray:
    """Wrap angles into [-offset * period, (1 - offset) * period)."""
    return angle - np.floor(angle / period + offset) * period


def observation_angle(boxes: np.ndarray, calib: Calibration) -> np.ndarray:
    """(N, 7) LiDAR boxes -> (N,) KITTI alpha = rotation_y - atan2(x, z) of the camera centre."""
    location, _, rotation_y = lidar_to_kitti_camera_boxes(boxes, calib)
    return limit_period(rotation_y - np.arctan2(location[:, 0], location[:, 2]))


# ---------------------------------------------------------------------------------------------
# 2D IoU


def _box_areas(boxes: np.ndarray) -> np.ndarray:
    return np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)


def pairwise_intersection_2d(boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    """(N, 4), (M, 4) xyxy -> (N, M) intersection areas in square pixels."""
    boxes1 = np.asarray(boxes1, dtype=np.float64).reshape(-1, 4)
    boxes2 = np.asarray(boxes2, dtype=np.float64).reshape(-1, 4)
    top_left = np.maximum(boxes1[:, None, :2], boxes2[None, :, :2])
    bottom_right = np.minimum(boxes1[:, None, 2:], boxes2[None, :, 2:])
    wh = np.clip(bottom_right - top_left, 0, None)
    return wh[..., 0] * wh[..., 1]


def pairwise_iou_2d(boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    """(N, 4), (M, 4) xyxy -> (N, M) IoU in [0, 1]; 0 where the union is empty."""
    boxes1 = np.asarray(boxes1, dtype=np.float64).reshape(-1, 4)
    boxes2 = np.asarray(boxes2, dtype=np.float64).reshape(-1, 4)
    inter = pairwise_intersection_2d(boxes1, boxes2)
    union = _box_areas(boxes1)[:, None] + _box_areas(boxes2)[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def pairwise_giou_2d(boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    """(N, 4), (M, 4) xyxy -> (N, M) generalised IoU in [-1, 1] (Rezatofighi et al. 2019)."""
    boxes1 = np.asarray(boxes1, dtype=np.float64).reshape(-1, 4)
    boxes2 = np.asarray(boxes2, dtype=np.float64).reshape(-1, 4)
    inter = pairwise_intersection_2d(boxes1, boxes2)
    union = _box_areas(boxes1)[:, None] + _box_areas(boxes2)[None, :] - inter
    iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
    top_left = np.minimum(boxes1[:, None, :2], boxes2[None, :, :2])
    bottom_right = np.maximum(boxes1[:, None, 2:], boxes2[None, :, 2:])
    wh = np.clip(bottom_right - top_left, 0, None)
    hull = wh[..., 0] * wh[..., 1]
    return iou - np.where(hull > 0, (hull - union) / np.where(hull > 0, hull, 1.0), 0.0)


# ---------------------------------------------------------------------------------------------
# Rotated bird's-eye-view and 3D IoU


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z of (a - o) x (b - o) over the last axis (size 2)."""
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (
        b[..., 0] - o[..., 0]
    )


def _inside_convex(points: np.ndarray, polygon: np.ndarray, tolerance: float) -> np.ndarray:
    """points (K, P, 2), counter-clockwise polygon (K, 4, 2) -> (K, P) inside or on the boundary."""
    start = polygon[:, None, :, :]
    end = np.roll(polygon, -1, axis=1)[:, None, :, :]
    side = _cross(start, end, points[:, :, None, :])
    return np.all(side >= -tolerance, axis=2)


def convex_quad_intersection_area(quads1: np.ndarray, quads2: np.ndarray) -> np.ndarray:
    """(K, 4, 2), (K, 4, 2) counter-clockwise convex quadrilaterals -> (K,) intersection areas.

    Exact up to floating point: the intersection polygon's vertices are the corners of each
    quad inside the other plus all edge-edge crossings; they are ordered by angle around their
    centroid and the shoelace formula gives the area.
    """
    k = quads1.shape[0]
    if k == 0:
        return np.zeros(0)
    scale = np.maximum(np.abs(quads1).max(axis=(1, 2)), np.abs(quads2).max(axis=(1, 2))) + 1.0
    tolerance = (1e-9 * scale**2)[:, None]

    inside1 = _inside_convex(quads1, quads2, tolerance[..., None])
    inside2 = _inside_convex(quads2, quads1, tolerance[..., None])

    # Edge i of quad 1 against edge j of quad 2: p + t r = q + u s.
    p = quads1[:, :, None, :]
    r = (np.roll(quads1, -1, axis=1) - quads1)[:, :, None, :]
    q = quads2[:, None, :, :]
    s = (np.roll(quads2, -1, axis=1) - quads2)[:, None, :, :]
    denominator = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    qp = q - p
    parallel = np.abs(denominator) < 1e-12 * scale[:, None, None] ** 2
    safe = np.where(parallel, 1.0, denominator)
    t = (qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]) / safe
    u = (qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]) / safe
    eps = 1e-12
    crossing = ~parallel & (t >= -eps) & (t <= 1 + eps) & (u >= -eps) & (u <= 1 + eps)
    crossing_points = (p + t[..., None] * r).reshape(k, 16, 2)

    candidates = np.concatenate([quads1, quads2, crossing_points], axis=1)
    valid = np.concatenate([inside1, inside2, crossing.reshape(k, 16)], axis=1)
    count = valid.sum(axis=1)

    centroid = (candidates * valid[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    offset = candidates - centroid[:, None, :]
    angle = np.where(valid, np.arctan2(offset[..., 1], offset[..., 0]), np.inf)
    order = np.argsort(angle, axis=1)
    ordered = np.take_along_axis(candidates, order[..., None], axis=1)
    ordered_valid = np.take_along_axis(valid, order, axis=1)
    # Pad with the first vertex: the repeated points add zero-area terms to the shoelace sum.
    ordered = np.where(ordered_valid[..., None], ordered, ordered[:, :1, :])
    following = np.roll(ordered, -1, axis=1)
    twice_area = (ordered[..., 0] * following[..., 1] - ordered[..., 1] * following[..., 0]).sum(1)
    return np.where(count >= 3, 0.5 * np.abs(twice_area), 0.0)


def paired_bev_intersection(
    boxes1: np.ndarray, boxes2: np.ndarray, chunk: int = 65536
) -> np.ndarray:
    """(K, 7), (K, 7) boxes -> (K,) rotated bird's-eye-view intersection areas of row pairs."""
    boxes1 = np.asarray(boxes1, dtype=np.float64).reshape(-1, 7)
    boxes2 = np.asarray(boxes2, dtype=np.float64).reshape(-1, 7)
    areas = np.zeros(boxes1.shape[0])
    # Only pairs whose circumscribed circles meet can intersect.
    radius1 = 0.5 * np.hypot(boxes1[:, 3], boxes1[:, 4])
    radius2 = 0.5 * np.hypot(boxes2[:, 3], boxes2[:, 4])
    distance = np.hypot(boxes1[:, 0] - boxes2[:, 0], boxes1[:, 1] - boxes2[:, 1])
    candidates = np.flatnonzero(distance < radius1 + radius2)
    for start in range(0, candidates.size, chunk):
        rows = candidates[start : start + chunk]
        areas[rows] = convex_quad_intersection_area(
            bev_corners(boxes1[rows]), bev_corners(boxes2[rows])
        )
    return areas


def paired_iou_bev(boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    """(K, 7), (K, 7) -> (K,) rotated BEV IoU of row pairs."""
    boxes1 = np.asarray(boxes1, dtype=np.float64).reshape(-1, 7)
    boxes2 = np.asarray(boxes2, dtype=np.float64).reshape(-1, 7)
    inter = paired_bev_intersection(boxes1, boxes2)
    union = boxes1[:, 3] * boxes1[:, 4] + boxes2[:, 3] * boxes2[:, 4] - inter
    return np.clip(np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0), 0.0, 1.0)


def paired_iou_3d(boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    """(K, 7), (K, 7) -> (K,) rotated 3D IoU of row pairs (boxes upright, yaw about z)."""
    boxes1 = np.asarray(boxes1, dtype=np.float64).reshape(-1, 7)
    boxes2 = np.asarray(boxes2, dtype=np.float64).reshape(-1, 7)
    bev = paired_bev_intersection(boxes1, boxes2)
    top = np.minimum(boxes1[:, 2] + boxes1[:, 5] / 2, boxes2[:, 2] + boxes2[:, 5] / 2)
    bottom = np.maximum(boxes1[:, 2] - boxes1[:, 5] / 2, boxes2[:, 2] - boxes2[:, 5] / 2)
    inter = bev * np.clip(top - bottom, 0, None)
    union = np.prod(boxes1[:, 3:6], axis=1) + np.prod(boxes2[:, 3:6], axis=1) - inter
    return np.clip(np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0), 0.0, 1.0)


def _pairwise(paired, boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    boxes1 = np.asarray(boxes1, dtype=np.float64).reshape(-1, 7)
    boxes2 = np.asarray(boxes2, dtype=np.float64).reshape(-1, 7)
    rows, cols = np.meshgrid(np.arange(len(boxes1)), np.arange(len(boxes2)), indexing="ij")
    return paired(boxes1[rows.ravel()], boxes2[cols.ravel()]).reshape(len(boxes1), len(boxes2))


def pairwise_iou_bev(boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    """(N, 7), (M, 7) boxes -> (N, M) exact rotated bird's-eye-view IoU."""
    return _pairwise(paired_iou_bev, boxes1, boxes2)


def pairwise_iou_3d(boxes1: np.ndarray, boxes2: np.ndarray) -> np.ndarray:
    """(N, 7), (M, 7) boxes -> (N, M) exact rotated 3D IoU."""
    return _pairwise(paired_iou_3d, boxes1, boxes2)


def points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(P, >=3) points, (N, 7) boxes -> (N, P) bool: point inside (or on) box.

    Each box tests only the points of the x-strip its bird's-eye-view circumcircle spans
    (points sorted by x once, the strip found by binary search), so a frame's 100,000 points
    cost each box a few thousand exact tests instead of all of them."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    inside = np.zeros((len(boxes), len(xyz)), dtype=bool)
    if len(boxes) == 0 or len(xyz) == 0:
        return inside
    order = np.argsort(xyz[:, 0])
    sorted_x = xyz[order, 0]
    half = boxes[:, 3:6] / 2
    # A point inside a box lies within its circumcircle; the margin covers rounding.
    reach = np.hypot(half[:, 0], half[:, 1]) * (1 + 1e-9) + 1e-9
    starts = np.searchsorted(sorted_x, boxes[:, 0] - reach, side="left")
    stops = np.searchsorted(sorted_x, boxes[:, 0] + reach, side="right")
    for row, (box, start, stop) in enumerate(zip(boxes, starts, stops, strict=True)):
        candidates = order[start:stop]
        offset = xyz[candidates] - box[:3]
        c, s = np.cos(box[6]), np.sin(box[6])
        local_x = offset[:, 0] * c + offset[:, 1] * s
        local_y = -offset[:, 0] * s + offset[:, 1] * c
        hit = (
            (np.abs(local_x) <= half[row, 0])
            & (np.abs(local_y) <= half[row, 1])
            & (np.abs(offset[:, 2]) <= half[row, 2])
        )
        inside[row, candidates[hit]] = True
    return inside


def nearest_in_bev(boxes: np.ndarray, others: np.ndarray, max_distance: float) -> np.ndarray:
    """(N,) row of the box of others (M, 7+) whose bird's-eye-view centre is nearest each box
    of boxes (N, 7+), when closer than max_distance metres; else -1."""
    if len(others) == 0 or len(boxes) == 0:
        return np.full(len(boxes), -1, dtype=np.int64)
    distance = np.linalg.norm(boxes[:, None, :2] - others[None, :, :2], axis=2)
    nearest = distance.argmin(axis=1)
    close = distance[np.arange(len(boxes)), nearest] < max_distance
    return np.where(close, nearest, -1)
