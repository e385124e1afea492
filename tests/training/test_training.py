import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from commands.main import main
from detmatch.checkpoints import list_checkpoints, load_checkpoint
from detmatch.config import ConfigError, load_config
from detmatch.data.kitti import KittiDataset, read_objects
from detmatch.geometry import pairwise_iou_2d
from detmatch.models.build import load_detectors
from detmatch.training.distributed import StepSampler, init_distributed
from detmatch.training.trainer import SupervisedTrainer, leave_cores_for_workers
from tests.conftest import REPO

TINY = REPO / "configs" / "tiny.toml"


def write_config(path: Path, extra: str) -> Path:
    path.write_text(TINY.read_text() + "\n" + extra)
    return path


def assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_config_rejects_unknown_keys_and_bad_types(tmp_path):
    (tmp_path / "a.toml").write_text("[train]\nstepz = 3\n")
    with pytest.raises(ConfigError, match=r"a.toml: unknown key 'stepz' in \[train\]"):
        load_config(tmp_path / "a.toml")
    (tmp_path / "b.toml").write_text("[trian]\nsteps = 3\n")
    with pytest.raises(ConfigError, match=r"unknown section \[trian\]"):
        load_config(tmp_path / "b.toml")
    (tmp_path / "c.toml").write_text('[train]\nsteps = "many"\n')
    with pytest.raises(ConfigError, match=r"\[train\] steps must be int"):
        load_config(tmp_path / "c.toml")
    config = load_config(TINY)
    assert config.train.steps == 6 and config.detector2d.widths == (8, 16, 16, 32)


def test_step_sampler_resumes_the_same_stream():
    full = StepSampler(10, 3, seed=1, start_step=0)
    resumed = StepSampler(10, 3, seed=1, start_step=4)
    stream = iter(full)
    first = [next(stream) for _ in range(3 * 8)]
    stream = iter(resumed)
    assert [next(stream) for _ in range(3 * 4)] == first[12:]
    # Each epoch visits every frame once.
    assert sorted(i for i, _ in first[:10]) == list(range(10))
    # Two ranks of batch 2 split the frames one rank of batch 4 would take, draws included.
    rank0 = iter(StepSampler(10, 2, seed=1, start_step=0, rank=0, world_size=2))
    rank1 = iter(StepSampler(10, 2, seed=1, start_step=0, rank=1, world_size=2))
    single = iter(StepSampler(10, 4, seed=1, start_step=0))
    assert [next(rank0), next(rank0), next(rank1), next(rank1)] == [next(single) for _ in range(4)]


def test_train_cli_writes_metrics_checkpoints_and_predictions(synth_root, tmp_path):
    run = tmp_path / "run"
    assert main(["train", "--config", str(TINY), "--data", str(synth_root), "--out", str(run)]) == 0
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if "loss_2d" in r] == [1, 2, 3, 4, 5, 6]
    evaluation = [r["eval"] for r in records if "eval" in r]
    assert len(evaluation) == 1 and set(evaluation[0]["3d"]) == {
        "Car",
        "Pedestrian",
        "Cyclist",
        "mAP",
    }
    assert [p.name for p in list_checkpoints(run)] == ["step_00000003.pt", "step_00000006.pt"]
    state = load_checkpoint(list_checkpoints(run)[-1])
    assert state["step"] == 6 and state["classes"] == ["Car", "Pedestrian", "Cyclist"]
    assert {"model_2d", "model_3d", "optimizer_2d", "optimizer_3d", "rng"} <= state.keys()

    out = tmp_path / "pred"
    assert (
        main(
            [
                "predict",
                "--checkpoint",
                str(run),
                "--data",
                str(synth_root),
                "--split",
                "val",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    val_ids = KittiDataset(synth_root).ids("val")
    for modality in ("2d", "3d"):
        assert sorted(p.stem for p in (out / modality).iterdir()) == sorted(val_ids)
    two_d = read_objects(out / "2d" / f"{val_ids[0]}.txt")
    assert not two_d.has_3d.any()
    json_out = tmp_path / "eval.json"
    ids_file = synth_root / "ImageSets" / "val.txt"
    gt_dir = synth_root / "training" / "label_2"
    for modality in ("2d", "3d"):
        args = [
            "eval",
            "--gt-dir",
            str(gt_dir),
            "--pred-dir",
            str(out / modality),
            "--ids-file",
            str(ids_file),
            "--json",
            str(json_out),
        ]
        assert main(args) == 0
        assert "Car" in json.loads(json_out.read_text())


def test_killed_run_resumes_to_the_same_weights(synth_root, tmp_path):
    config = write_config(tmp_path / "c.toml", "")
    config_text = (
        config.read_text()
        .replace("steps = 6", "steps = 10")
        .replace("checkpoint_every = 3", "checkpoint_every = 2")
        .replace("eval_every = 6", "eval_every = 1000")
    )
    config.write_text(config_text)
    base = [
        sys.executable,
        "-m",
        "commands.main",
        "train",
        "--config",
        str(config),
        "--data",
        str(synth_root),
    ]
    subprocess.run([*base, "--out", str(tmp_path / "whole")], check=True, capture_output=True)

    killed = subprocess.Popen(
        [*base, "--out", str(tmp_path / "killed")],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 120
    while not (tmp_path / "killed" / "checkpoints" / "step_00000004.pt").exists():
        assert killed.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    os.kill(killed.pid, signal.SIGKILL)
    killed.wait()
    steps_done = [p.name for p in list_checkpoints(tmp_path / "killed")]
    assert "step_00000010.pt" not in steps_done
    subprocess.run(
        [*base, "--out", str(tmp_path / "killed"), "--resume"], check=True, capture_output=True
    )

    whole = load_checkpoint(tmp_path / "whole" / "checkpoints" / "step_00000010.pt")
    resumed = load_checkpoint(tmp_path / "killed" / "checkpoints" / "step_00000010.pt")
    for key in ("model_2d", "model_3d"):
        assert_same_weights(whole[key], resumed[key])
    assert whole["optimizer_3d"]["state"].keys() == resumed["optimizer_3d"]["state"].keys()


def test_a_cpu_run_leaves_a_core_per_data_worker_and_restores_its_threads(
    synth_root, tmp_path, monkeypatch
):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    context = init_distributed("cpu")
    cores = len(os.sched_getaffinity(0))
    before = torch.get_num_threads()
    try:
        assert leave_cores_for_workers(0, context) == before == torch.get_num_threads()
        assert leave_cores_for_workers(1, context) == max(1, cores - 1) == torch.get_num_threads()
        assert leave_cores_for_workers(cores + 3, context) == 1 == torch.get_num_threads()
        torch.set_num_threads(before)
        monkeypatch.setenv("OMP_NUM_THREADS", str(before))
        assert leave_cores_for_workers(1, context) == before == torch.get_num_threads()
        monkeypatch.delenv("OMP_NUM_THREADS")

        config = load_config(write_config(tmp_path / "c.toml", "")).replace(
            "data", root=str(synth_root), num_workers=1
        )
        config = config.replace("train", steps=2, eval_every=1000, checkpoint_every=1000)
        trainer = SupervisedTrainer(config, tmp_path / "run", context)
        seen = []
        step = trainer.train_step
        trainer.train_step = lambda batch: seen.append(torch.get_num_threads()) or step(batch)
        trainer.run()
        assert seen == [max(1, cores - 1)] * 2
        assert torch.get_num_threads() == before
    finally:
        torch.set_num_threads(before)


def test_two_process_torchrun_keeps_ranks_identical(synth_root, tmp_path):
    worker = REPO / "tests" / "training" / "ddp_worker.py"
    torchrun = Path(sys.executable).parent / "torchrun"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    subprocess.run(
        [
            str(torchrun),
            "--standalone",
            "--nproc_per_node",
            "2",
            str(worker),
            str(TINY),
            str(synth_root),
            str(tmp_path),
        ],
        check=True,
        env=env,
        capture_output=True,
        timeout=300,
    )
    rank0 = torch.load(tmp_path / "rank0_of_2.pt", weights_only=True)
    rank1 = torch.load(tmp_path / "rank1_of_2.pt", weights_only=True)
    for key in ("model_2d", "model_3d"):
        assert_same_weights(rank0[key], rank1[key])
    # Rank 0 alone logged and checkpointed; training moved the weights.
    steps = [
        json.loads(l)["step"]
        for l in (tmp_path / "metrics.jsonl").read_text().splitlines()
        if "loss_2d" in l
    ]
    assert steps == [1, 2, 3, 4, 5, 6]
    loaded = load_detectors(tmp_path)
    config, model_2d = loaded.config, loaded.model_2d
    assert_same_weights(model_2d.state_dict(), rank0["model_2d"])
    fresh = SupervisedTrainer(
        config.replace("data", root=str(synth_root)), tmp_path / "fresh", init_distributed()
    )
    assert not torch.equal(
        fresh.state.model_2d.stages[0][0][0].weight, model_2d.stages[0][0][0].weight
    )


def test_overfits_a_few_frames(synth_root, tmp_path):
    """A real learning test: the tiny detectors, trained briefly on four frames, find their cars."""
    config = load_config(TINY).replace("data", root=str(synth_root))
    config = config.replace(
        "train",
        steps=150,
        eval_every=1000,
        checkpoint_every=1000,
        log_every=50,
        flip_probability=0.0,
        lr_2d=0.02,
        lr_3d=0.004,
        warmup_steps=10,
    )
    trainer = SupervisedTrainer(config, tmp_path / "run", init_distributed())
    state = trainer.run()
    from detmatch.data.dataset import collate
    from detmatch.inference import predict_batch

    batch = collate([trainer.train_set[i] for i in range(len(trainer.train_set))])
    found_2d = found_3d = total = 0
    for sample, (det_2d, det_3d) in zip(
        batch.samples, predict_batch(state.model_2d, state.model_3d, batch), strict=True
    ):
        frame = trainer.train_set.kitti.load_frame(sample.frame_id)
        labels = frame.labels
        cars = (labels.names == "Car") & (labels.occluded <= 1) & (labels.boxes_2d.heights >= 20)
        for box_2d, box_3d in zip(
            labels.boxes_2d.xyxy[cars], labels.boxes_3d.data[cars], strict=True
        ):
            total += 1
            car_2d = det_2d[(det_2d.classes == 0) & (det_2d.scores > 0.3)]
            found_2d += bool(len(car_2d)) and pairwise_iou_2d(box_2d, car_2d.boxes).max() > 0.5
            car_3d = det_3d[(det_3d.classes == 0) & (det_3d.scores > 0.3)]
            if len(car_3d):
                distance = np.hypot(*(car_3d.boxes[:, :2] - box_3d[:2]).T).min()
                found_3d += distance < 1.0
    assert total >= 3
    assert found_2d >= 0.8 * total and found_3d >= 0.8 * total


def test_init_2d_starts_the_camera_from_another_runs_weights(synth_root, tmp_path):
    """[train] init_2d (the benchmark's COCO stand-in): the 2D detector starts from another
    run's, the 3D detector from the seed's fresh weights; a different 2D design is refused."""
    config = load_config(TINY).replace("data", root=str(synth_root))
    SupervisedTrainer(config, tmp_path / "camera", init_distributed()).run()
    camera = load_checkpoint(list_checkpoints(tmp_path / "camera")[-1])
    fresh = SupervisedTrainer(config, tmp_path / "fresh", init_distributed()).state

    started = SupervisedTrainer(
        config.replace("train", init_2d=str(tmp_path / "camera")),
        tmp_path / "started", init_distributed(),
    ).state  # fmt: skip

    assert_same_weights(started.model_2d.state_dict(), camera["model_2d"])
    assert_same_weights(started.model_3d.state_dict(), fresh.model_3d.state_dict())
    fresh_2d = fresh.model_2d.state_dict()
    assert any(not torch.equal(fresh_2d[k], v) for k, v in camera["model_2d"].items())
    other = config.replace("detector2d", head_width=24).replace(
        "train", init_2d=str(tmp_path / "camera")
    )
    with pytest.raises(ValueError, match="init_2d .*step_00000006.pt: its \\[detector2d\\]"):
        SupervisedTrainer(other, tmp_path / "refused", init_distributed())


def test_3d_background_is_learned_only_inside_the_camera_view(synth_root):
    from detmatch.data.dataset import FrameDataset
    from detmatch.models.common import heatmap_focal_loss
    from detmatch.models.detector3d import PointPillars3D

    config = load_config(TINY)
    model = PointPillars3D(config.detector3d, 3)
    dataset = FrameDataset(
        synth_root, "train", config.data.classes, config.data.image_size, model.grid
    )
    sample = dataset[0]
    area = model.build_targets(sample.gt_3d, sample.camera_view).labelled_area[0] > 0
    centres = model.cell_centres()
    ahead = np.abs(centres[..., 1]) < 0.2 * centres[..., 0]
    beside = np.abs(centres[..., 1]) > 1.5 * centres[..., 0]  # beyond KITTI's ~81 degree view
    assert area[ahead].all() and not area[beside].any()

    target = np.zeros((1, 3, *area.shape), dtype=np.float32)
    confident_outside = torch.where(torch.from_numpy(area)[None, None], -8.0, 8.0).expand(
        1, 3, *area.shape
    )
    quiet = torch.full((1, 3, *area.shape), -8.0)
    mask = torch.from_numpy(area[None, None].astype(np.float32))
    assert heatmap_focal_loss(confident_outside, torch.from_numpy(target), mask) == pytest.approx(
        float(heatmap_focal_loss(quiet, torch.from_numpy(target), mask)), abs=1e-6
    )
    assert heatmap_focal_loss(
        confident_outside, torch.from_numpy(target)
    ) > 100 * heatmap_focal_loss(quiet, torch.from_numpy(target))


def test_a_bf16_training_step_agrees_with_fp32(synth_root, tmp_path):
    """The same first step under [train] precision fp32 and bf16: the forward passes run in
    bfloat16 (autocast), the losses come back fp32 and agree within bf16's precision."""
    records = {}
    for precision in ("fp32", "bf16"):
        config = load_config(TINY).replace("data", root=str(synth_root))
        config = config.replace("train", precision=precision, flip_probability=0.0)
        trainer = SupervisedTrainer(config, tmp_path / precision, init_distributed())
        assert trainer.autocast_dtype == (torch.bfloat16 if precision == "bf16" else None)
        batch = next(trainer.batches())
        records[precision] = trainer.train_step(batch)
        outputs = trainer.run_2d(batch.images)
        assert all(o.dtype == torch.float32 for o in outputs)
    fp32, bf16 = records["fp32"], records["bf16"]
    for key in ("loss_2d", "loss_3d"):
        assert bf16[key] == pytest.approx(fp32[key], rel=0.05), key
    assert bf16["loss_2d"] != fp32["loss_2d"]  # bf16 really ran
    with pytest.raises(ConfigError, match=r"\[train\] precision must be one of"):
        load_config(TINY).replace("train", precision="fp16")


def test_signed_box_errors_match_confident_detections_to_nearby_truth():
    from detmatch.structures import Detections
    from detmatch.training.evaluation import signed_box_errors, summarise_errors

    truth = np.array([[10.0, 0.0, -0.9, 4.0, 1.6, 1.5, 0.0], [30.0, 5.0, -0.9, 4.0, 1.6, 1.5, 0.0]])
    boxes = np.array([
        [10.3, 0.2, -1.0, 3.2, 1.7, 1.5, 0.1],  # 0.8 m short, near the first car
        [30.0, 5.0, -0.9, 4.5, 1.6, 1.4, 0.0],  # 0.5 m long, the second car
        [50.0, 0.0, -0.9, 4.0, 1.6, 1.5, 0.0],  # nothing near: ignored
        [10.0, 0.0, -0.9, 9.0, 9.0, 9.0, 0.0],  # not confident: ignored
    ])  # fmt: skip
    probabilities = np.array([[0.9, 0, 0], [0.8, 0, 0], [0.9, 0, 0], [0.2, 0, 0]])
    detections = Detections(boxes, probabilities[:, 0], np.zeros(4, dtype=int), probabilities)
    errors = signed_box_errors(detections, truth)
    np.testing.assert_allclose(errors, [[-0.8, 0.1, 0.0, -0.1], [0.5, 0.0, -0.1, 0.0]], atol=1e-9)
    summary = summarise_errors([errors, np.zeros((0, 4))])
    assert summary["count"] == 2 and summary["l"] == pytest.approx(-0.15)
    assert summarise_errors([])["l"] is None
