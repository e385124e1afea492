"""Writing a synthetic data set in KITTI layout, frames in parallel worker processes.

Frame i of a data set depends only on (seed, i, resolution, world): the files are
byte-identical whatever the number of workers.
"""

from __future__ import annotations

import json
import multiprocessing
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from detmatch.data.kitti import write_frame, write_image_set
from detmatch.data.synth.camera import Visibility, render_camera
from detmatch.data.synth.labels import make_labels
from detmatch.data.synth.layout import sample_scene
from detmatch.data.synth.lidar import lidar_sweep
from detmatch.data.synth.scene import Scene
from detmatch.data.synth.sensors import RESOLUTIONS, make_camera, make_lidar
from detmatch.data.synth.textures import NoiseTiles
from detmatch.data.synth.world import DEFAULT_WORLD, get_world
from detmatch.files import atomic_write_bytes
from detmatch.structures import Frame

GENERATOR_VERSION = "1.0"


@dataclass(frozen=True)
class SynthFrame:
    """A generated frame with what made it: the scene and each object's visibility."""

    frame: Frame
    scene: Scene
    visibility: Visibility


def frame_id(index: int) -> str:
    """KITTI frame id: six digits."""
    return f"{index:06d}"


def generate_frame(
    seed: int, index: int, resolution: str = "half", world: str = DEFAULT_WORLD
) -> SynthFrame:
    """Sample, render and label frame `index` of the data set made with `seed` in `world`."""
    sensors = get_world(world)
    return render_scene(sample_scene(seed, index, sensors), frame_id(index), resolution, world)


def render_scene(
    scene: Scene, frame_name: str, resolution: str = "half", world: str = DEFAULT_WORLD
) -> SynthFrame:
    """Render the camera image and LiDAR sweep of a scene and label it."""
    camera = make_camera(resolution)
    noise = NoiseTiles(scene.texture_seed)
    render = render_camera(scene, camera, noise)
    points = lidar_sweep(scene, make_lidar(), noise, get_world(world))
    labels = make_labels(scene, camera, render.visibility)
    frame = Frame(frame_name, render.image, points, camera.calib, labels)
    return SynthFrame(frame, scene, render.visibility)


def _write_one(task: tuple[str, int, int, str, str]) -> int:
    out_dir, seed, index, resolution, world = task
    write_frame(out_dir, generate_frame(seed, index, resolution, world).frame)
    return index


def split_ids(num_frames: int, val_fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """(train ids, val ids), each sorted: a seeded shuffle puts round(val_fraction * n) frames
    in val; with val_fraction > 0 and two frames or more, each split gets at least one."""
    num_val = int(round(val_fraction * num_frames))
    if val_fraction > 0 and num_frames >= 2:
        num_val = min(max(num_val, 1), num_frames - 1)
    num_val = min(num_val, num_frames - 1)
    order = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2**31,))).permutation(
        num_frames
    )
    val = sorted(int(i) for i in order[:num_val])
    train = sorted(int(i) for i in order[num_val:])
    return [frame_id(i) for i in train], [frame_id(i) for i in val]


def _check_arguments(
    num_frames: int, seed: int, resolution: str, workers: int, val_fraction: float
) -> None:
    if (
        isinstance(num_frames, bool)
        or not isinstance(num_frames, (int, np.integer))
        or num_frames < 1
    ):
        raise ValueError(f"num_frames must be an integer >= 1, got {num_frames!r}")
    if num_frames > 999_999:
        raise ValueError(
            f"num_frames must be at most 999999 (six-digit frame ids), got {num_frames}"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {sorted(RESOLUTIONS)}, got {resolution!r}")
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if not (0.0 <= val_fraction < 1.0):
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction!r}")


def generate_dataset(
    out_dir: Path,
    num_frames: int,
    seed: int,
    resolution: str = "half",
    workers: int = 1,
    val_fraction: float = 0.25,
    progress: bool = True,
    world: str = DEFAULT_WORLD,
) -> None:
    """Write a synthetic paired camera + LiDAR data set in KITTI layout under out_dir:
    training/{image_2, velodyne, calib, label_2}, ImageSets/{train, val, trainval}.txt and
    synth.json (generator version, world version, seed, resolution, frame count).

    resolution: "full" (1242x375) or "half" (621x188); workers: processes (1 = this one);
    world: a version of world.WORLDS (how the sensors fail).
    """
    _check_arguments(num_frames, seed, resolution, workers, val_fraction)
    get_world(world)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tasks = [
        (os.fspath(out_dir), int(seed), index, resolution, world) for index in range(num_frames)
    ]
    bar = tqdm(total=num_frames, desc="synth", unit="frame", disable=not progress)
    with bar:
        if workers == 1 or num_frames == 1:
            for task in tasks:
                _write_one(task)
                bar.update()
        else:
            context = multiprocessing.get_context("spawn")
            with context.Pool(min(workers, num_frames)) as pool:
                for _ in pool.imap_unordered(_write_one, tasks):
                    bar.update()
    train, val = split_ids(num_frames, val_fraction, int(seed))
    write_image_set(out_dir / "ImageSets" / "train.txt", train)
    write_image_set(out_dir / "ImageSets" / "val.txt", val)
    write_image_set(
        out_dir / "ImageSets" / "trainval.txt", [frame_id(i) for i in range(num_frames)]
    )
    width, height, _ = RESOLUTIONS[resolution]
    record = {
        "generator": "detmatch.data.synth",
        "version": GENERATOR_VERSION,
        "world": world,
        "seed": int(seed),
        "resolution": resolution,
        "image_size": [width, height],
        "frames": int(num_frames),
        "val_fraction": float(val_fraction),
    }
    atomic_write_bytes(out_dir / "synth.json", (json.dumps(record, indent=2) + "\n").encode())
