"""benchmarks/ssl_benchmark.py: the configs of its teacher-student runs (no training here)."""

import argparse
import shutil

from benchmarks.camera_init import camera_config
from benchmarks.ssl_benchmark import splits, ssl_config, stand_in_base
from detmatch.config import load_config
from detmatch.data.kitti import read_image_set
from detmatch.matching_policy import MatchingPolicy
from tests.conftest import REPO

TINY = REPO / "configs" / "tiny.toml"


def run_config(synth_root, tmp_path, method: str, lr_factor: float | None, steps: int | None = 40):
    """The benchmark's splits on a copy of the tiny synthetic set, and `method`'s run config."""
    data = tmp_path / "data"
    shutil.copytree(synth_root, data)
    args = argparse.Namespace(
        data=str(data), fraction=0.25, seed=0, dev_fraction=0.25, ssl_steps=steps,
        ssl_lr_factor=lr_factor,
    )  # fmt: skip
    labeled, unlabeled, dev = splits(args)
    base = load_config(TINY).replace("data", root=str(data), train_split=labeled, val_split=dev)
    return data, (labeled, unlabeled, dev), base, ssl_config(base, method, args, tmp_path / "runs")


def test_runs_start_from_the_pretraining_at_its_rates_times_the_factor(synth_root, tmp_path):
    _, (labeled, _, _), base, config = run_config(synth_root, tmp_path, "detmatch", lr_factor=0.5)

    assert config.ssl.method == "detmatch"
    assert config.ssl.pretrained == str(tmp_path / "runs" / "pretrain")
    assert (config.train.lr_2d, config.train.lr_3d) == (base.train.lr_2d / 2, base.train.lr_3d / 2)
    assert (config.train.schedule_2d, config.train.schedule_3d) == ("constant", "constant")
    assert config.train.steps == 40
    assert config.train.eval_every == 20  # dev halfway and at the end
    assert config.data.train_split == labeled


def test_without_a_factor_or_steps_runs_take_the_configs_ssl_stage(synth_root, tmp_path):
    _, _, base, config = run_config(synth_root, tmp_path, "confidence", lr_factor=None, steps=None)

    assert (config.train.lr_2d, config.train.lr_3d) == (base.ssl.lr_2d, base.ssl.lr_3d)
    assert config.train.steps == base.ssl.steps
    assert config.train.warmup_steps == base.ssl.warmup_steps
    assert config.train.eval_every == base.ssl.steps // 2


def test_the_every_label_run_trains_on_labeled_and_unlabeled_frames_not_dev(synth_root, tmp_path):
    data, (labeled, unlabeled, dev), _, config = run_config(
        synth_root, tmp_path, "every-label", lr_factor=1.0
    )

    sets = data / "ImageSets"
    frames = {name: set(read_image_set(sets / f"{name}.txt")) for name in (labeled, unlabeled, dev)}
    every = set(read_image_set(sets / f"{config.data.train_split}.txt"))
    assert frames[labeled] and frames[unlabeled] and frames[dev]
    assert every == frames[labeled] | frames[unlabeled]
    assert every == set(read_image_set(sets / "train.txt")) - frames[dev]
    assert config.ssl.method == "labeled-only-control"  # the stage's schedule, no pseudo-labels
    assert config.data.val_split == dev


def test_the_pseudo_label_report_follows_the_configs_detmatch_rule():
    """With tau_3d_unmatched on, the report's DetMatch 3D labels add the in-view box the camera
    missed; its 2D labels stay the matched ones (a LiDAR-only label has no 2D box)."""
    from types import SimpleNamespace

    import numpy as np

    from benchmarks.ssl_benchmark import pseudo_label_sets
    from detmatch.data.kitti import read_calib
    from detmatch.geometry import project_boxes_to_image
    from detmatch.structures import Detections
    from tests.conftest import KITTI_SAMPLE

    calib = read_calib(KITTI_SAMPLE / "training" / "calib" / "000001.txt")
    image = (1242, 375)
    car = [15.0, 2.0, -0.9, 3.9, 1.6, 1.5, 0.2]
    person = [12.0, -4.0, -0.8, 0.6, 0.6, 1.8, 0.0]
    probabilities_3d = np.array([[0.8, 0.1, 0.1], [0.1, 0.7, 0.1]])
    det_3d = Detections(np.array([car, person]), probabilities_3d.max(1),
                        probabilities_3d.argmax(1), probabilities_3d)  # fmt: skip
    det_2d = Detections(project_boxes_to_image(np.array([car]), calib, image), np.array([0.85]),
                        np.array([0]), np.array([[0.85, 0.05, 0.1]]))  # fmt: skip
    sample = SimpleNamespace(calib=calib, image_transform=SimpleNamespace(original_size=image))
    classes = ("Car", "Pedestrian", "Cyclist")

    def detmatch_rows(config):
        rows = pseudo_label_sets(det_2d, det_3d, sample, classes, config)["detmatch"]
        in_3d = rows.boxes_3d.data.any(axis=1)
        return sorted(rows.names[in_3d]), sorted(rows.names[~in_3d])

    base = load_config(TINY)
    assert detmatch_rows(base.replace("ssl", tau_3d_unmatched=1.0)) == (["Car"], ["Car"])
    lidar_only = base.replace("ssl", tau_3d_unmatched=0.6)
    assert detmatch_rows(lidar_only) == (["Car", "Pedestrian"], ["Car"])


def test_every_benchmark_method_is_a_valid_config():
    """A method whose overrides name a deleted option or contradict each other would only fail
    hours into a benchmark run."""
    from benchmarks.ssl_benchmark import METHODS
    from detmatch.config import apply_overrides

    base = load_config(TINY)
    for method, overrides in METHODS.items():
        assert apply_overrides(base, overrides).ssl.method != "labeled-only", method
    detmatch = apply_overrides(base, METHODS["detmatch"]).ssl
    assert MatchingPolicy.from_config(detmatch).tau_3d_unmatched == 0.6
    matched_only = apply_overrides(base, METHODS["detmatch-matched-only"]).ssl
    assert MatchingPolicy.from_config(matched_only).tau_3d_unmatched is None


def test_the_stand_in_trains_on_camera_set_never_on_the_runs_overrides(tmp_path):
    args = argparse.Namespace(
        config=str(TINY),
        set=["train.lr_2d=0.002"],
        camera_set=["train.precision=fp32", "train.checkpoint_every=7"],
    )
    config = camera_config(stand_in_base(args), tmp_path / "camera", steps=30)
    tiny = load_config(TINY)
    assert config.train.lr_2d == tiny.train.lr_2d != 0.002
    assert (config.train.precision, config.train.checkpoint_every) == ("fp32", 7)
    assert (config.train.steps, config.train.init_2d, config.data.train_split) == (30, "", "train")
