"""A tiny trained checkpoint and its exported model repository, shared by tests/export and
tests/serving. Both conftests register these fixtures; the work is done once per session and
kept in pytest's base temporary directory."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import KITTI_SAMPLE, REPO


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """PyTorch on one thread: on a small shared machine its OpenMP pool can run hundreds of
    times slower than one thread while another process holds the cores."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _trained_checkpoint(base: Path, synth_root: Path) -> Path:
    run = base / "onnx_shared" / "run"
    if not (run / "checkpoints").is_dir():
        from commands.main import main

        with one_torch_thread():
            assert main(["train", "--config", str(REPO / "configs" / "tiny.toml"),
                         "--data", str(synth_root), "--out", str(run)]) == 0  # fmt: skip
    return run


def _exported_repository(base: Path, synth_root: Path) -> Path:
    repository = base / "onnx_shared" / "repository"
    if not (repository / "000001" / "manifest.json").is_file():
        from export.onnx_export import export_checkpoint

        checkpoint = _trained_checkpoint(base, synth_root)
        with one_torch_thread():
            export_checkpoint(
                checkpoint,
                repository,
                promote_version=True,
                parity_data=[KITTI_SAMPLE],
                synthetic_frames=2,
            )
    return repository


@pytest.fixture(scope="session")
def trained_checkpoint(tmp_path_factory, synth_root) -> Path:
    """Run directory of configs/tiny.toml trained on the 6 synthetic frames."""
    return _trained_checkpoint(tmp_path_factory.getbasetemp(), synth_root)


@pytest.fixture(scope="session")
def exported_repository(tmp_path_factory, synth_root) -> Path:
    """A model repository whose version 000001 (promoted) is the tiny checkpoint, exported
    with parity on 2 synthetic frames and the KITTI sample frames."""
    return _exported_repository(tmp_path_factory.getbasetemp(), synth_root)


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    with one_torch_thread():
        yield


@pytest.fixture(scope="session")
def served_labeler(exported_repository):
    """The exported version 000001 as the service loads it, warmed up."""
    from serving.labeler import Labeler

    labeler = Labeler.from_repository(exported_repository)
    labeler.warm_up()
    return labeler
