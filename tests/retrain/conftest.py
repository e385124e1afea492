"""Fixtures of the retraining tests: a writable copy of the tiny exported repository (version
000001, promoted, its checkpoint kept), a copy of the six synthetic frames with a labeled split,
an unlabeled split and the val gate, and helpers that run `detmatch retrain`."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from detmatch.data.kitti import read_image_set, write_image_set
from tests.conftest import REPO
from tests.onnx_fixtures import (  # noqa: F401
    _one_torch_thread,
    exported_repository,
    trained_checkpoint,
)

# The tiny config's [ssl] unlabeled_split is its val split, the gate: a round needs these.
SPLITS = ("--set", "data.train_split=labeled", "--set", "ssl.unlabeled_split=unlabeled")


@pytest.fixture
def repository(tmp_path, exported_repository) -> Path:  # noqa: F811
    return Path(shutil.copytree(exported_repository, tmp_path / "models"))


@pytest.fixture
def round_data(tmp_path, synth_root) -> Path:
    """The six synthetic frames: 2 labeled, 2 unlabeled (of train), 2 val (the gate)."""
    root = Path(shutil.copytree(synth_root, tmp_path / "data"))
    train = read_image_set(root / "ImageSets" / "train.txt")
    write_image_set(root / "ImageSets" / "labeled.txt", train[:2])
    write_image_set(root / "ImageSets" / "unlabeled.txt", train[2:])
    return root


def retrain_args(store: Path, data: Path, repository: Path, *extra: str) -> list[str]:
    return ["retrain", "--store", str(store), "--data", str(data), "--repository",
            str(repository), *SPLITS, *extra]  # fmt: skip


def retrain_process(*args: str, **popen) -> subprocess.Popen:
    """`detmatch retrain ARGS` as a separate process (one torch thread), stdout and stderr
    piped as text."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        [sys.executable, "-m", "commands.main", *args], cwd=REPO, env=env, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, **popen,
    )  # fmt: skip
