"""The synthetic paired data set: layout, determinism, labels against geometry, failure modes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from detmatch.data.kitti import KittiDataset, read_image_set
from detmatch.data.synth import (
    generate_dataset,
    generate_frame,
    render_scene,
    sample_scene,
    split_ids,
)
from detmatch.data.synth.layout import Placer, sample_lighting, sample_road
from detmatch.data.synth.scene import frame_rng
from detmatch.geometry import (
    lidar_to_image,
    pairwise_iou_2d,
    pairwise_iou_bev,
    points_in_boxes,
    project_boxes_to_image,
)

SEED = 7
FRAMES = 6


def _generate(out: Path, workers: int, seed: int = SEED, frames: int = FRAMES) -> Path:
    generate_dataset(out, frames, seed, "half", workers, val_fraction=0.25, progress=False)
    return out


def _all_files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _generate(tmp_path_factory.mktemp("synth") / "one_worker", workers=1)


@pytest.fixture(scope="module")
def frames(dataset_dir: Path) -> list:
    dataset = KittiDataset(dataset_dir)
    return [dataset.load_frame(frame_id) for frame_id in dataset.ids("trainval")]


def test_generation_is_byte_identical_whatever_the_workers(
    dataset_dir: Path, tmp_path: Path
) -> None:
    again = _all_files(_generate(tmp_path / "two_workers", workers=2))
    first = _all_files(dataset_dir)
    assert sorted(again) == sorted(first)
    assert not [name for name in first if not name.endswith(".tmp") and first[name] != again[name]]
    assert not [name for name in first if name.endswith(".tmp")], "temporary files left behind"


def test_different_seed_gives_different_frames() -> None:
    a, b = generate_frame(SEED, 0), generate_frame(SEED + 1, 0)
    assert not np.array_equal(a.frame.image, b.frame.image)
    assert a.frame.points.shape != b.frame.points.shape or not np.array_equal(
        a.frame.points, b.frame.points
    )


def test_kitti_layout_readable(dataset_dir: Path, frames: list) -> None:
    ids = [f"{i:06d}" for i in range(FRAMES)]
    for kind, suffix in (
        ("image_2", ".png"),
        ("velodyne", ".bin"),
        ("calib", ".txt"),
        ("label_2", ".txt"),
    ):
        assert sorted(p.name for p in (dataset_dir / "training" / kind).iterdir()) == [
            i + suffix for i in ids
        ]
    train = read_image_set(dataset_dir / "ImageSets" / "train.txt")
    val = read_image_set(dataset_dir / "ImageSets" / "val.txt")
    assert read_image_set(dataset_dir / "ImageSets" / "trainval.txt") == ids
    assert sorted(train + val) == ids and len(val) == 2 and not set(train) & set(val)
    record = json.loads((dataset_dir / "synth.json").read_text())
    assert record["seed"] == SEED and record["frames"] == FRAMES and record["resolution"] == "half"
    assert record["version"]
    for frame in frames:
        assert frame.image.shape == (188, 621, 3) and frame.image.dtype == np.uint8
        assert frame.points.dtype == np.float32 and frame.points.shape[1] == 4
        assert len(frame.points) > 50_000
        assert frame.calib.P2[0, 0] == pytest.approx(721.5377 / 2)
        assert frame.labels is not None and np.sum(frame.labels.names != "DontCare") > 0
        assert set(frame.labels.names) <= {"Car", "Van", "Pedestrian", "Cyclist", "DontCare"}


def test_full_resolution(tmp_path: Path) -> None:
    generate_dataset(tmp_path, 1, 3, "full", 1, 0.25, progress=False)
    frame = KittiDataset(tmp_path).load_frame("000000")
    assert frame.image.shape == (375, 1242, 3)
    assert frame.calib.P2[0, 0] == pytest.approx(721.5377)
    assert frame.calib.P2[1, 2] == pytest.approx(172.854)
    assert read_image_set(tmp_path / "ImageSets" / "val.txt") == []


def test_lidar_sweep_like_a_64_beam_sensor(frames: list) -> None:
    points = frames[0].points
    distance = np.hypot(points[:, 0], points[:, 1])
    assert (points[:, 0] < -5).any(), "the sweep covers more than the camera's field of view"
    assert distance.max() <= 100.5 and np.all((points[:, 3] >= 0) & (points[:, 3] <= 1))
    assert points[:, 2].min() > -1.73 - 0.15, "nothing below the road"
    # Fixed angular resolution: far fewer returns per square metre of ground far away.
    ground = points[:, 2] < -1.6
    near = np.sum(ground & (distance > 5) & (distance < 10)) / (np.pi * (10**2 - 5**2))
    far = np.sum(ground & (distance > 20) & (distance < 25)) / (np.pi * (25**2 - 20**2))
    assert near > 8 * far


def test_labels_fit_projection_and_points(frames: list) -> None:
    """Untruncated (truncation < 0.05) labelled objects: the projected 3D box is within 10 px
    of the 2D label box at camera depth >= 10 m (within 16 px nearer: a person does not fill
    the corners of the box). Objects under 40 m with occlusion level <= 1 have LiDAR points in
    their 3D box (the file's box, after the KITTI text round trip)."""
    checked = 0
    for frame in frames:
        labels = frame.labels
        real = labels.names != "DontCare"
        untruncated = real & (labels.truncated < 0.05)
        boxes = labels.boxes_3d.data[untruncated]
        projected = project_boxes_to_image(boxes, frame.calib, frame.image_size)
        difference = np.abs(projected - labels.boxes_2d.xyxy[untruncated]).max(axis=1)
        _, depth = lidar_to_image(boxes[:, :3], frame.calib)
        assert np.all(difference <= np.where(depth >= 10.0, 10.0, 16.0)), difference
        close = real & (np.hypot(labels.boxes_3d.data[:, 0], labels.boxes_3d.data[:, 1]) < 40)
        close &= labels.occluded <= 1
        counts = points_in_boxes(frame.points, labels.boxes_3d.data[close]).sum(axis=1)
        assert np.all(counts >= 3), counts
        checked += int(untruncated.sum())
    assert checked >= 10


def test_labels_are_consistent(frames: list) -> None:
    for frame in frames:
        labels = frame.labels
        real = labels.names != "DontCare"
        xyxy = labels.boxes_2d.xyxy
        assert np.all(xyxy[:, 0] >= 0) and np.all(xyxy[:, 2] <= 620) and np.all(xyxy[:, 3] <= 187)
        assert np.all(xyxy[:, 2] >= xyxy[:, 0]) and np.all(xyxy[:, 3] >= xyxy[:, 1])
        assert np.all((labels.truncated[real] >= 0) & (labels.truncated[real] <= 1))
        assert set(labels.occluded[real]) <= {0, 1, 2} and np.all(labels.occluded[~real] == -1)
        assert np.all(np.hypot(labels.boxes_3d.data[real, 0], labels.boxes_3d.data[real, 1]) < 72)


def test_occlusion_and_truncation_vary(frames: list) -> None:
    occluded = np.concatenate([f.labels.occluded[f.labels.names != "DontCare"] for f in frames])
    truncated = np.concatenate([f.labels.truncated[f.labels.names != "DontCare"] for f in frames])
    assert {0, 1, 2} <= set(occluded.tolist())
    assert (truncated > 0.05).any() and (truncated == 0).any()


def _scene_with(cars: list[tuple[float, float]], seed: int = 11):
    """A scene with only the given cars at road positions (s, u offset from the ego lane)."""
    rng = frame_rng(seed, 0)
    road = sample_road(rng)
    placer = Placer(rng, road)
    for s, du in cars:
        assert placer.place("Car", placer.road_user("Car"), s, road.ego_offset + du, 0.0)
    return placer.scene(sample_lighting(rng), 1)


def _rows_by_object(scene, labels) -> dict[int, int]:
    """Scene object index -> label row, matched by 3D box centre (DontCare rows excluded)."""
    real = np.flatnonzero(labels.names != "DontCare")
    centres = scene.boxes()[:, :3]
    return {
        int(np.argmin(np.abs(centres - labels.boxes_3d.data[i, :3]).max(axis=1))): int(i)
        for i in real
    }


@pytest.mark.parametrize(
    ("behind_offset", "level"),
    [(1.6, 1), (0.8, 2), (0.3, None)],
    ids=["partly", "largely", "hidden"],
)
def test_occlusion_follows_rendered_visibility(behind_offset: float, level: int | None) -> None:
    """A car 8 m behind another, shifted sideways: occlusion level from the visible fraction of
    its silhouette; under 5 % visible it becomes DontCare. A car at the image edge is truncated."""
    scene = _scene_with([(12.0, 0.0), (20.0, behind_offset), (5.5, 4.0)])
    synth = render_scene(scene, "000000", "half")
    labels, visibility = synth.frame.labels, synth.visibility
    rows = _rows_by_object(scene, labels)
    assert labels.occluded[rows[0]] == 0 and labels.truncated[rows[0]] == 0.0
    fraction = visibility.visible_pixels[1] / visibility.full_pixels[1]
    if level is None:
        assert 1 not in rows and fraction < 0.05 and np.sum(labels.names == "DontCare") == 1
    else:
        assert labels.occluded[rows[1]] == level and labels.names[rows[1]] == "Car"
        assert (fraction >= 0.4) == (level == 1)
    assert 0.1 < labels.truncated[rows[2]] < 0.9 and labels.occluded[rows[2]] == 0


def test_clutter_is_pedestrian_sized_and_unlabelled(frames: list) -> None:
    for index in range(FRAMES):
        scene = sample_scene(SEED, index)
        clutter = scene.boxes("clutter")
        assert len(clutter) >= 3
        assert np.all((clutter[:, 5] >= 1.0) & (clutter[:, 5] <= 2.3))
        assert np.all(np.maximum(clutter[:, 3], clutter[:, 4]) <= 0.85)
        labelled = scene.boxes("labelled")
        for box in frames[index].labels.boxes_3d.data[frames[index].labels.names != "DontCare"]:
            assert np.abs(labelled[:, :3] - box[:3]).max(axis=1).min() < 0.02
            assert np.abs(clutter[:, :2] - box[:2]).max(axis=1).min() > 0.1


def test_objects_never_intersect() -> None:
    for index in range(3):
        boxes = sample_scene(SEED, index).boxes("all")
        iou = pairwise_iou_bev(boxes, boxes)
        np.fill_diagonal(iou, 0.0)
        assert iou.max() == 0.0


def test_parked_rows_overlap_in_image_not_in_3d(frames: list) -> None:
    overlapping = 0
    for frame in frames:
        cars = frame.labels[np.isin(frame.labels.names, ["Car", "Van"])]
        iou_2d = pairwise_iou_2d(cars.boxes_2d.xyxy, cars.boxes_2d.xyxy)
        iou_bev = pairwise_iou_bev(cars.boxes_3d.data, cars.boxes_3d.data)
        upper = np.triu(np.ones_like(iou_2d, dtype=bool), 1)
        assert np.all(iou_bev[upper] < 0.01)
        overlapping += int(np.sum(upper & (iou_2d > 0.3) & (iou_bev == 0)))
    assert overlapping >= 1


def test_split_ids_and_argument_checks(tmp_path: Path) -> None:
    train, val = split_ids(10, 0.25, 0)
    assert len(val) == 2 and sorted(train + val) == [f"{i:06d}" for i in range(10)]
    assert split_ids(10, 0.25, 0) == (train, val) and split_ids(10, 0.25, 1) != (train, val)
    assert len(split_ids(3, 0.01, 0)[1]) == 1 and split_ids(1, 0.5, 0) == (["000000"], [])
    assert split_ids(5, 0.0, 0)[1] == []
    for kwargs, message in (
        ({"num_frames": 0}, "num_frames"),
        ({"val_fraction": 1.0}, "val_fraction"),
        ({"val_fraction": -0.1}, "val_fraction"),
        ({"resolution": "quarter"}, "resolution"),
        ({"workers": 0}, "workers"),
    ):
        arguments = {
            "out_dir": tmp_path,
            "num_frames": 1,
            "seed": 0,
            "resolution": "half",
            "workers": 1,
            "val_fraction": 0.25,
            "progress": False,
        } | kwargs
        with pytest.raises(ValueError, match=message):
            generate_dataset(**arguments)
