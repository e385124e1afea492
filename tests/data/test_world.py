"""World versions: recorded in the data set and read back, v1 and v3 unchanged, v2
deterministic, its people-shaped clutter seen by both sensors and never labelled; the camera
stand-in's set shares no scene with the benchmark's."""

from __future__ import annotations

import json
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from benchmarks.camera_init import check_disjoint
from detmatch.data.synth import Scene, generate_dataset, generate_frame, sample_scene
from detmatch.data.synth.camera import render_camera
from detmatch.data.synth.primitives import Primitives
from detmatch.data.synth.sensors import make_camera
from detmatch.data.synth.textures import NoiseTiles
from detmatch.data.synth.world import WORLDS, get_world, read_resolution, read_world
from detmatch.geometry import points_in_boxes
from tests.conftest import KITTI_SAMPLE

NEW_KINDS = ("clutter/pay_station", "clutter/shrub", "clutter/bicycles")


def test_the_world_is_written_into_the_data_set_and_read_back(tmp_path: Path) -> None:
    generate_dataset(tmp_path / "v2", 2, seed=3, world="v2", progress=False)
    assert json.loads((tmp_path / "v2" / "synth.json").read_text())["world"] == "v2"
    assert read_world(tmp_path / "v2") == "v2"

    old = tmp_path / "old"  # written before versions were recorded: the only world there was
    old.mkdir()
    (old / "synth.json").write_text(json.dumps({"generator": "detmatch.data.synth", "seed": 0}))
    assert read_world(old) == "v1"
    assert read_world(KITTI_SAMPLE) == ""

    with pytest.raises(ValueError, match="unknown world 'v9'.*'v1', 'v2'"):
        generate_dataset(tmp_path / "bad", 1, seed=0, world="v9", progress=False)
    with pytest.raises(ValueError, match="unknown world"):
        get_world("V2")


def test_v1_frames_are_those_every_earlier_result_was_measured_on() -> None:
    # Reference values of generator seed 7, frame 1, from the code before world versions
    # existed (compared with a tolerance: numpy versions may move the last bits).
    frame = generate_frame(7, 1).frame
    assert (
        list(frame.labels.names)
        == ["Car", "Van", "Car", "Car", "Van", "Van", "Car", "Van"] + ["Car"] * 6 + ["DontCare"] * 5
    )
    np.testing.assert_allclose(
        frame.labels.boxes_3d.data[:2],
        [
            [7.3604, 5.5568, -0.9675, 4.5108, 1.6424, 1.525, 3.1179],
            [24.2702, 4.5844, -0.6345, 5.9, 2.1323, 2.1911, 3.0793],
        ],
        atol=2e-4,
    )
    assert abs(len(frame.points) - 113608) <= 100
    assert frame.image.mean() == pytest.approx(68.8757, abs=0.05)
    assert frame.points[:, 3].mean() == pytest.approx(0.24275, abs=0.002)


def test_v2_is_deterministic_per_seed_and_differs_from_v1() -> None:
    a, b = generate_frame(5, 2, world="v2"), generate_frame(5, 2, world="v2")
    assert np.array_equal(a.frame.image, b.frame.image)
    assert np.array_equal(a.frame.points, b.frame.points)
    assert np.array_equal(a.frame.labels.boxes_3d.data, b.frame.labels.boxes_3d.data)
    v1 = generate_frame(5, 2, world="v1")
    assert not np.array_equal(a.frame.image, v1.frame.image)
    clutter = [o.kind for o in a.scene.objects if o.is_clutter]
    lo, hi = WORLDS["v2"].clutter_count
    assert lo <= len(clutter) < hi


def test_v3_frames_are_those_the_calibration_runs_c2_to_c4_used() -> None:
    # Reference values of generator seed 7, frame 2 (three pedestrians, a cyclist), from the
    # world code of d6d2343; the frames of calibration runs C2 to C4 (v3 since 30c2106).
    frame = generate_frame(7, 2, world="v3").frame
    names = list(frame.labels.names)
    assert names == ["Car"] * 6 + ["Van"] + ["Pedestrian"] * 3 + ["Cyclist"] + ["DontCare"] * 2
    boxes = frame.labels.boxes_3d.data
    np.testing.assert_allclose(
        boxes[[7, 10]],
        [
            [5.6099, -4.5675, -0.8257, 0.4174, 0.67, 1.8086, -2.698],
            [42.7944, -1.9013, -0.8843, 1.7574, 0.6241, 1.6914, 0.0435],
        ],
        atol=2e-4,
    )
    assert abs(len(frame.points) - 113615) <= 100
    assert frame.image.mean() == pytest.approx(76.0650, abs=0.05)
    assert frame.points[:, 3].mean() == pytest.approx(0.23597, abs=0.002)


def _new_clutter_in_view() -> list[tuple]:
    """(frame, object index, kind) of v2's new clutter kinds 4-40 m ahead, in the image."""
    found = []
    camera = make_camera("half")
    for index in range(8):
        synth = generate_frame(11, index, world="v2")
        for i, thing in enumerate(synth.scene.objects):
            (u, v), depth = camera.project(thing.box[:3])
            in_image = 0 <= u < camera.width and 0 <= v < camera.height
            if thing.kind in NEW_KINDS and 4.0 < depth < 40.0 and in_image:
                found.append((synth, i, thing.kind))
    return found


def _without(scene: Scene, index: int) -> Scene:
    """The scene with object `index`'s primitives taken out."""
    keep = scene.primitives.owner != index
    prims = Primitives(*(getattr(scene.primitives, f.name)[keep] for f in fields(Primitives)))
    return replace(scene, primitives=prims)


def test_new_clutter_shows_in_both_sensors_and_is_never_labelled() -> None:
    found = _new_clutter_in_view()
    assert {kind for _, _, kind in found} == set(NEW_KINDS)
    seen = {kind: [] for kind in NEW_KINDS}  # (LiDAR points, synth, index); many stand behind cars
    for synth, i, kind in found:
        box = synth.scene.objects[i].box
        points = int(points_in_boxes(synth.frame.points[:, :3], box[None]).sum())
        seen[kind].append((points, synth, i))
        labels = synth.frame.labels
        real = labels.boxes_3d.data[labels.names != "DontCare"]
        if len(real):
            assert np.hypot(*(real[:, :2] - box[:2]).T).min() > 0.1, kind
    camera = make_camera("half")
    for kind, things in seen.items():
        points, synth, i = max(things, key=lambda thing: thing[0])
        assert points >= 3, (kind, [thing[0] for thing in things])
        # In the image: taking the LiDAR's best-seen one out of the scene changes pixels.
        image = render_camera(_without(synth.scene, i), camera, NoiseTiles(0)).image
        again = render_camera(synth.scene, camera, NoiseTiles(0)).image
        assert np.any(image != again, axis=-1).sum() >= 10, kind


def test_people_lose_more_returns_in_v2_and_more_again_in_v3() -> None:
    def points_per_person(world: str) -> float:
        counts = []
        for index in range(6):
            synth = generate_frame(13, index, world=world)
            people = synth.frame.labels.boxes_3d.data[synth.frame.labels.names == "Pedestrian"]
            if len(people):
                counts += list(points_in_boxes(synth.frame.points[:, :3], people).sum(axis=1))
        return float(np.mean(counts))

    v1, v2, v3 = (points_per_person(world) for world in ("v1", "v2", "v3"))
    assert v3 < 0.95 * v2 < 0.95 * 0.95 * v1


def test_the_crowded_world_has_more_people_and_cyclists_and_is_v3_otherwise() -> None:
    def count(world: str, kind: str) -> int:
        return sum(
            sum(o.kind == kind for o in sample_scene(21, i, WORLDS[world]).objects)
            for i in range(6)
        )

    for kind in ("Pedestrian", "Cyclist"):
        assert count("v3-crowd", kind) > 2 * count("v3", kind), kind
    crowd, v3 = WORLDS["v3-crowd"], WORLDS["v3"]
    assert replace(crowd, name="v3", pedestrian_groups=v3.pedestrian_groups,
                   cyclists=v3.cyclists) == v3  # fmt: skip


def test_the_camera_stand_in_set_shares_no_seed_or_scene_with_the_benchmark(
    tmp_path: Path,
) -> None:
    generate_dataset(tmp_path / "bench", 3, seed=0, world="v2", progress=False)
    generate_dataset(tmp_path / "camera", 3, seed=7, world="v2", progress=False)
    generate_dataset(tmp_path / "same", 2, seed=0, world="v2", progress=False)
    check_disjoint(tmp_path / "camera", tmp_path / "bench")
    with pytest.raises(SystemExit, match="share generator seed 0"):
        check_disjoint(tmp_path / "same", tmp_path / "bench")
    bench = [sample_scene(0, i, WORLDS["v2"]) for i in range(3)]
    camera = [sample_scene(7, i, WORLDS["v2"]) for i in range(3)]
    assert not {s.texture_seed for s in bench} & {s.texture_seed for s in camera}
    for a in bench:
        for b in camera:
            assert a.road != b.road


def test_the_stand_in_set_must_be_rendered_at_the_benchmark_s_resolution(tmp_path: Path) -> None:
    generate_dataset(tmp_path / "bench", 1, seed=0, world="v2", resolution="full", progress=False)
    generate_dataset(tmp_path / "half", 1, seed=7, world="v2", progress=False)
    generate_dataset(tmp_path / "full", 1, seed=7, world="v2", resolution="full", progress=False)
    assert (read_resolution(tmp_path / "bench"), read_resolution(tmp_path / "half")) == (
        "full",
        "half",
    )
    assert read_resolution(KITTI_SAMPLE) == ""
    check_disjoint(tmp_path / "full", tmp_path / "bench")
    with pytest.raises(SystemExit, match="rendered at half resolution .* at full"):
        check_disjoint(tmp_path / "half", tmp_path / "bench")
