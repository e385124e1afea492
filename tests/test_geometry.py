import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from detmatch.data.kitti import read_calib
from detmatch.geometry import (
    box3d_corners,
    convex_quad_intersection_area,
    kitti_camera_to_lidar_boxes,
    lidar_to_image,
    lidar_to_kitti_camera_boxes,
    lidar_to_rect,
    limit_period,
    observation_angle,
    pairwise_giou_2d,
    pairwise_iou_2d,
    pairwise_iou_3d,
    pairwise_iou_bev,
    points_in_boxes,
    project_boxes_to_image,
    rect_to_lidar,
    upright_boxes_from_camera,
)
from tests.conftest import KITTI_SAMPLE

coordinate = st.floats(-50, 50, allow_nan=False)
size = st.floats(0.2, 8, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False)


@st.composite
def boxes_2d(draw):
    x1, y1 = draw(coordinate), draw(coordinate)
    return np.array([x1, y1, x1 + draw(size), y1 + draw(size)])


@st.composite
def boxes_3d(draw):
    return np.array(
        [draw(coordinate), draw(coordinate), draw(st.floats(-3, 3)), draw(size), draw(size),
         draw(size), draw(angle)]
    )  # fmt: skip


@st.composite
def nearby_box_pairs(draw):
    """Two 3D boxes close enough to overlap often."""
    a = draw(boxes_3d())
    b = a + np.array([draw(st.floats(-3, 3)) for _ in range(3)] + [0, 0, 0, draw(angle)])
    b[3:6] = [draw(size), draw(size), draw(size)]
    return a, b


# --- 2D IoU ---------------------------------------------------------------------------------


@given(boxes_2d(), boxes_2d())
def test_iou_2d_symmetric_and_bounded(a, b):
    ab, ba = pairwise_iou_2d(a, b)[0, 0], pairwise_iou_2d(b, a)[0, 0]
    assert ab == pytest.approx(ba, abs=1e-12)
    assert 0.0 <= ab <= 1.0
    assert pairwise_iou_2d(a, a)[0, 0] == pytest.approx(1.0, abs=1e-12)


@given(boxes_2d(), boxes_2d(), coordinate, coordinate)
def test_iou_2d_translation_invariant(a, b, dx, dy):
    shift = np.array([dx, dy, dx, dy])
    assert pairwise_iou_2d(a + shift, b + shift)[0, 0] == pytest.approx(
        pairwise_iou_2d(a, b)[0, 0], abs=1e-9
    )


@given(boxes_2d(), boxes_2d())
def test_giou_bounds_and_relation_to_iou(a, b):
    giou = pairwise_giou_2d(a, b)[0, 0]
    assert -1.0 <= giou <= pairwise_iou_2d(a, b)[0, 0] + 1e-12
    assert pairwise_giou_2d(a, a)[0, 0] == pytest.approx(1.0)


def test_iou_and_giou_hand_computed():
    a = np.array([[0.0, 0.0, 2.0, 2.0]])
    b = np.array([[1.0, 0.0, 3.0, 2.0], [4.0, 0.0, 6.0, 2.0]])
    np.testing.assert_allclose(pairwise_iou_2d(a, b), [[2 / 6, 0.0]])
    # Second pair: union 8, hull 12 -> GIoU = 0 - (12 - 8) / 12.
    np.testing.assert_allclose(pairwise_giou_2d(a, b), [[2 / 6 - 0.0, -4 / 12]])
    assert pairwise_iou_2d(a, np.zeros((0, 4))).shape == (1, 0)


# --- rotated BEV / 3D IoU --------------------------------------------------------------------


@settings(max_examples=200)
@given(nearby_box_pairs())
def test_iou_3d_symmetric_bounded_and_identity(pair):
    a, b = pair
    for iou in (pairwise_iou_bev, pairwise_iou_3d):
        ab, ba = iou(a, b)[0, 0], iou(b, a)[0, 0]
        assert ab == pytest.approx(ba, abs=1e-9)
        assert 0.0 <= ab <= 1.0
        assert iou(a, a)[0, 0] == pytest.approx(1.0, abs=1e-9)


@settings(max_examples=200)
@given(nearby_box_pairs(), angle, coordinate, coordinate, st.floats(-2, 2))
def test_iou_3d_invariant_under_rigid_motion(pair, theta, dx, dy, dz):
    a, b = pair
    c, s = np.cos(theta), np.sin(theta)

    def move(box):
        moved = box.copy()
        moved[0] = c * box[0] - s * box[1] + dx
        moved[1] = s * box[0] + c * box[1] + dy
        moved[2] = box[2] + dz
        moved[6] = box[6] + theta
        return moved

    for iou in (pairwise_iou_bev, pairwise_iou_3d):
        assert iou(move(a), move(b))[0, 0] == pytest.approx(iou(a, b)[0, 0], abs=1e-7)


def test_bev_iou_hand_computed():
    square = np.array([0, 0, 0, 2, 2, 2, 0.0])
    turned = np.array([0, 0, 0, 2, 2, 2, np.pi / 4])
    # A square and itself rotated by 45 degrees: the overlap is a regular octagon.
    octagon = 8 * (np.sqrt(2) - 1)
    assert pairwise_iou_bev(square, turned)[0, 0] == pytest.approx(octagon / (8 - octagon))
    shifted = square + np.array([1, 0, 1, 0, 0, 0, 0])
    assert pairwise_iou_bev(square, shifted)[0, 0] == pytest.approx(2 / 6)
    # 3D: half the BEV overlap times half the height -> 2 / (16 - 2).
    assert pairwise_iou_3d(square, shifted)[0, 0] == pytest.approx(2 / 14)
    far = square + np.array([10, 0, 0, 0, 0, 0, 0])
    assert pairwise_iou_3d(square, far)[0, 0] == 0.0


@settings(max_examples=40)
@given(nearby_box_pairs())
def test_bev_intersection_matches_grid_sampling(pair):
    """Independent check: count grid cells whose centres lie in both rectangles."""
    a, b = pair
    corners = box3d_corners(np.stack([a, b]))[:, :4, :2]
    area = convex_quad_intersection_area(corners[:1], corners[1:])[0]
    low = np.minimum(corners[0].min(0), corners[1].min(0))
    high = np.maximum(corners[0].max(0), corners[1].max(0))
    step = 0.02
    xs, ys = np.meshgrid(np.arange(low[0], high[0], step) + step / 2,
                         np.arange(low[1], high[1], step) + step / 2)  # fmt: skip
    grid = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    flat = np.stack([a, b]).copy()
    flat[:, 2], flat[:, 5] = 0.0, 1.0
    inside = points_in_boxes(grid, flat)
    sampled = np.logical_and(inside[0], inside[1]).sum() * step**2
    perimeter = 2 * (a[3] + a[4])
    assert area == pytest.approx(sampled, abs=perimeter * step * 2 + 1e-6)


# --- frames and projection -------------------------------------------------------------------


@pytest.fixture(scope="module")
def calib():
    return read_calib(KITTI_SAMPLE / "training" / "calib" / "000001.txt")


@settings(max_examples=100)
@given(
    st.floats(-30, 30), st.floats(-3, 3), st.floats(2, 60), st.floats(0.3, 4), st.floats(0.3, 4),
    st.floats(0.3, 6), angle,
)  # fmt: skip
def test_kitti_label_round_trip(x, y, z, h, w, l, ry):
    calib = read_calib(KITTI_SAMPLE / "training" / "calib" / "000001.txt")
    location = np.array([[x, y, z]])
    boxes = kitti_camera_to_lidar_boxes(location, [[h, w, l]], [ry], calib)
    back_location, back_dims, back_ry = lidar_to_kitti_camera_boxes(boxes, calib)
    np.testing.assert_allclose(back_location, location, atol=1e-9)
    np.testing.assert_allclose(back_dims, [[h, w, l]], atol=1e-12)
    assert limit_period(back_ry - ry)[0] == pytest.approx(0.0, abs=1e-9)


def test_rect_lidar_inverse(calib):
    points = np.random.default_rng(0).normal(size=(20, 3)) * 10
    np.testing.assert_allclose(
        rect_to_lidar(lidar_to_rect(points, calib), calib), points, atol=1e-9
    )


def test_upright_frame_preserves_iou(calib):
    rng = np.random.default_rng(1)
    location = rng.uniform([-5, 1, 5], [5, 2, 30], size=(6, 3))
    dims = rng.uniform(1, 4, size=(6, 3))
    ry = rng.uniform(-np.pi, np.pi, 6)
    shifted = location + rng.normal(scale=0.5, size=(6, 3))
    lidar = pairwise_iou_3d(kitti_camera_to_lidar_boxes(location, dims, ry, calib),
                            kitti_camera_to_lidar_boxes(shifted, dims, ry, calib))  # fmt: skip
    upright = pairwise_iou_3d(upright_boxes_from_camera(location, dims, ry),
                              upright_boxes_from_camera(shifted, dims, ry))  # fmt: skip
    # The LiDAR frame differs from the upright camera frame by R0_rect and Tr's small tilts.
    np.testing.assert_allclose(lidar, upright, atol=0.03)


def test_projection_follows_design_formula(calib):
    box = np.array([[20.0, 1.0, -0.9, 4.0, 1.7, 1.5, 0.4]])
    corners = box3d_corners(box)[0]
    homogeneous = np.concatenate([corners, np.ones((8, 1))], axis=1)
    projected = (calib.P2 @ calib.lidar_to_rect @ homogeneous.T).T
    u, v = projected[:, 0] / projected[:, 2], projected[:, 1] / projected[:, 2]
    expected = [u.min(), v.min(), u.max(), v.max()]
    np.testing.assert_allclose(project_boxes_to_image(box, calib, (1242, 375))[0], expected)


def test_projection_clips_to_the_image_and_survives_boxes_behind(calib):
    behind = np.array(
        [[-10.0, 0.0, -1.0, 4.0, 1.7, 1.5, 0.0], [2.0, 0.0, -1.0, 8.0, 1.7, 1.5, 0.0]]
    )
    xyxy = project_boxes_to_image(behind, calib, (1242, 375))
    assert np.all(np.isfinite(xyxy))
    assert np.all(xyxy[:, [0, 2]] >= 0) and np.all(xyxy[:, [0, 2]] <= 1241)
    assert np.all(xyxy[:, [1, 3]] >= 0) and np.all(xyxy[:, [1, 3]] <= 374)


def test_observation_angle_matches_kitti_definition(calib):
    box = np.array([[15.0, 5.0, -0.8, 4.0, 1.7, 1.5, 0.3]])
    location, _, ry = lidar_to_kitti_camera_boxes(box, calib)
    expected = ry[0] - np.arctan2(location[0, 0], location[0, 2])
    assert observation_angle(box, calib)[0] == pytest.approx(limit_period(np.array(expected)))


def test_lidar_to_image_depth_is_forward_distance(calib):
    uv, depth = lidar_to_image(np.array([[30.0, 0.0, 0.0]]), calib)
    assert depth[0] == pytest.approx(30.0, abs=0.5)
    assert 0 < uv[0, 0] < 1242 and 0 < uv[0, 1] < 375


def test_points_in_boxes_rotated():
    box = np.array([[0, 0, 0, 4, 2, 2, np.pi / 2]])
    points = np.array([[0, 1.9, 0], [1.9, 0, 0], [0, 0, 0.99], [0, 0, 1.01]])
    assert points_in_boxes(points, box)[0].tolist() == [True, False, True, False]


def dense_points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """The definition: every point's offset rotated into every box's frame."""
    offset = points[None, :, :3].astype(np.float64) - boxes[:, None, :3]
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    local = (offset[..., 0] * c + offset[..., 1] * s, -offset[..., 0] * s + offset[..., 1] * c)
    half = boxes[:, None, 3:6] / 2
    return (
        (np.abs(local[0]) <= half[..., 0])
        & (np.abs(local[1]) <= half[..., 1])
        & (np.abs(offset[..., 2]) <= half[..., 2])
    )


@settings(max_examples=40, deadline=None)
@given(st.lists(boxes_3d(), min_size=0, max_size=12), st.integers(0, 2**31 - 1))
def test_points_in_boxes_agrees_with_the_dense_definition(boxes, seed):
    """The x-strip search finds exactly the points the all-pairs test does, corners and
    points just outside included."""
    boxes = np.array(boxes, dtype=np.float64).reshape(-1, 7)
    rng = np.random.default_rng(seed)
    points = rng.uniform([-55, -55, -6, 0], [55, 55, 6, 1], (3000, 4)).astype(np.float32)
    corners = box3d_corners(boxes).reshape(-1, 3) if len(boxes) else np.zeros((0, 3))
    edges = np.concatenate([corners, corners * (1 + 1e-7), boxes[:, :3]])
    points = np.concatenate([points, np.pad(edges, ((0, 0), (0, 1))).astype(np.float32)])
    inside = points_in_boxes(points, boxes)
    assert inside.shape == (len(boxes), len(points)) and inside.dtype == bool
    assert np.array_equal(inside, dense_points_in_boxes(points, boxes))


def test_serving_geometry_imports_no_torch():
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import detmatch.geometry, detmatch.structures, detmatch.data.kitti\n"
        "assert 'torch' not in [m for m in sys.modules if sys.modules[m] is not None]\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
