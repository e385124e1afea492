"""Training on the device the user picks: a clear error for CUDA without a GPU, and (on a GPU
machine) a DetMatch run whose models, batches and targets all live on the GPU."""

import json

import pytest
import torch

from commands.main import main
from detmatch.checkpoints import list_checkpoints, load_checkpoint
from tests.conftest import REPO

TINY = REPO / "configs" / "tiny.toml"
HAS_CUDA = torch.cuda.is_available()


@pytest.mark.skipif(HAS_CUDA, reason="checks the error on a machine without a GPU")
def test_cuda_without_a_gpu_is_a_clear_error(synth_root, tmp_path, capsys):
    args = ["train", "--config", str(TINY), "--data", str(synth_root), "--out", str(tmp_path)]
    assert main([*args, "--device", "cuda"]) == 2
    assert "no CUDA GPU" in capsys.readouterr().err
    assert not list_checkpoints(tmp_path)


@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA GPU (run on the GPU machine)")
def test_detmatch_trains_on_cuda(synth_root, tmp_path):
    args = ["train", "--config", str(TINY), "--data", str(synth_root), "--device", "cuda"]
    assert main([*args, "--out", str(tmp_path / "pre"), "--steps", "4"]) == 0
    assert main([*args, "--out", str(tmp_path / "ssl"), "--steps", "3", "--method", "detmatch",
                 "--pretrained", str(tmp_path / "pre"), "--preset", "paper"]) == 0  # fmt: skip
    records = [json.loads(line) for line in (tmp_path / "ssl" / "metrics.jsonl").open()]
    assert [r["step"] for r in records if "loss" in r][-1] == 3
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in records if "loss" in r)
    before = load_checkpoint(list_checkpoints(tmp_path / "pre")[-1])
    after = load_checkpoint(list_checkpoints(tmp_path / "ssl")[-1])
    assert after["model_3d"][next(iter(after["model_3d"]))].device.type == "cpu"
    for key in ("2d", "3d"):
        assert any(
            not torch.equal(before[f"model_{key}"][k], after[f"student_{key}"][k])
            for k in before[f"model_{key}"]
        )
