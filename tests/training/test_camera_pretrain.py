"""benchmarks/camera_pretrain.py: a 2D-only pre-training run, paired with a finished run's 3D
detector into a pre-training run that the teacher-student stage and the report can start from."""

import json

import pytest
import torch

from benchmarks.camera_pretrain import CameraTrainer, pair
from detmatch.checkpoints import list_checkpoints, load_checkpoint
from detmatch.cli import main
from detmatch.config import apply_overrides, load_config
from detmatch.models.build import load_detectors
from detmatch.training.distributed import init_distributed
from tests.conftest import REPO

TINY = REPO / "configs" / "tiny.toml"
WIDER_2D = ["detector2d.widths=[8, 16, 24, 32]", "data.image_size=[384, 128]"]


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_camera_run_trains_2d_only_and_pairs_with_a_lidar_run(synth_root, tmp_path):
    lidar_run = tmp_path / "joint"
    args = ["train", "--config", str(TINY), "--data", str(synth_root), "--out", str(lidar_run)]
    assert main(args) == 0
    config = apply_overrides(load_config(TINY), WIDER_2D).replace("data", root=str(synth_root))
    camera_run = tmp_path / "camera"
    trainer = CameraTrainer(config, camera_run, init_distributed("cpu"))
    fresh_3d = {k: v.clone() for k, v in trainer.state.model_3d.state_dict().items()}
    fresh_2d = {k: v.clone() for k, v in trainer.state.model_2d.state_dict().items()}
    state = trainer.run()

    assert same(state.model_3d.state_dict(), fresh_3d)
    assert not same(state.model_2d.state_dict(), fresh_2d)
    assert set(state.metrics) == {"2d", "full_2d"}

    paired = tmp_path / "paired"
    pair(camera_run, lidar_run, paired)
    checkpoint = load_checkpoint(list_checkpoints(paired)[-1])
    camera = load_checkpoint(list_checkpoints(camera_run)[-1])
    lidar = load_checkpoint(list_checkpoints(lidar_run)[-1])
    assert same(checkpoint["model_2d"], camera["model_2d"])
    assert same(checkpoint["model_3d"], lidar["model_3d"])
    assert checkpoint["config"]["detector2d"]["widths"] == [8, 16, 24, 32]
    assert checkpoint["config"]["detector3d"] == lidar["config"]["detector3d"]
    assert checkpoint["config"]["data"] == {**lidar["config"]["data"], "image_size": [384, 128]}
    assert checkpoint["step"] == 6
    curve = [json.loads(line) for line in (paired / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in curve] == [6]
    assert curve[0]["eval"]["2d"] == camera["metrics"]["2d"]
    assert curve[0]["eval"]["3d"] == lidar["metrics"]["3d"]
    loaded = load_detectors(paired)
    assert loaded.config.data.image_size == (384, 128)
    assert same(loaded.model_3d.state_dict(), lidar["model_3d"])


def test_pairing_refuses_runs_of_different_lengths(synth_root, tmp_path):
    lidar_run = tmp_path / "joint"
    args = ["train", "--config", str(TINY), "--data", str(synth_root), "--out", str(lidar_run)]
    assert main([*args, "--steps", "3"]) == 0
    config = load_config(TINY).replace("data", root=str(synth_root))
    CameraTrainer(config, tmp_path / "camera", init_distributed("cpu")).run()
    with pytest.raises(SystemExit, match="differs|steps differ"):
        pair(tmp_path / "camera", lidar_run, tmp_path / "paired")
