"""benchmarks/ssl_benchmark.py: the configs of its teacher-student runs (no training here)."""

import argparse
import shutil

from benchmarks.ssl_benchmark import splits, ssl_config
from detmatch.config import load_config
from detmatch.data.kitti import read_image_set
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
