import json
from pathlib import Path

import numpy as np
import pytest
import torch

from commands.main import main
from detmatch.checkpoints import list_checkpoints, load_checkpoint
from detmatch.config import (
    ExperimentConfig,
    apply_overrides,
    apply_preset,
    load_config,
    teacher_student_config,
)
from detmatch.data.augment import CloudTransform, strong_photometric
from detmatch.data.dataset import ImageTransform, flip_points
from detmatch.data.kitti import KittiDataset, read_calib
from detmatch.geometry import (
    limit_period,
    pairwise_iou_2d,
    points_in_boxes,
    project_boxes_to_image,
)
from detmatch.structures import Calibration
from detmatch.training.consistency import giou_torch, project_boxes_torch
from detmatch.training.distributed import init_distributed
from detmatch.training.ema import ema_decay, ema_update
from detmatch.training.semi_supervised import trainer_type
from tests.conftest import KITTI_SAMPLE, REPO

TINY = REPO / "configs" / "tiny.toml"


def random_boxes(rng, n):
    return np.column_stack(
        [rng.uniform(0, 50, n), rng.uniform(-20, 20, n), rng.uniform(-2, 0, n),
         rng.uniform(0.5, 5, n), rng.uniform(0.5, 2, n), rng.uniform(1, 2, n),
         rng.uniform(-np.pi, np.pi, n)]
    )  # fmt: skip


@pytest.mark.parametrize("seed", range(5))
def test_box_transforms_round_trip_between_frames(seed):
    rng = np.random.default_rng(seed)
    boxes = random_boxes(rng, 20)
    teacher = CloudTransform(flipped=bool(seed % 2))
    student = CloudTransform(
        teacher.flipped, rng.uniform(-np.pi / 4, np.pi / 4), rng.uniform(0.95, 1.05)
    )
    # un-augmented -> teacher frame -> un-augmented -> student frame -> un-augmented
    back = teacher.invert_boxes(teacher.apply_boxes(boxes))
    again = student.invert_boxes(student.apply_boxes(back))
    np.testing.assert_allclose(again[:, :6], boxes[:, :6], atol=1e-5)
    assert np.abs(limit_period(again[:, 6] - boxes[:, 6])).max() < 1e-5
    as_tensor = student.invert_boxes_torch(torch.from_numpy(student.apply_boxes(boxes)))
    np.testing.assert_allclose(as_tensor.numpy()[:, :6], boxes[:, :6], atol=1e-5)
    # Points move with their boxes: a point inside a box stays inside.
    points = np.column_stack([boxes[:, :3], np.zeros(20)])
    assert (
        points_in_boxes(student.apply_points(points), student.apply_boxes(boxes)).diagonal().all()
    )


def flipped_calibration(calib: Calibration, width: int) -> Calibration:
    """The calibration of the flipped pair: u -> W - u in the image, y -> -y in the cloud."""
    mirror_image = np.array([[-1.0, 0, width], [0, 1, 0], [0, 0, 1]])
    mirror_cloud = np.diag([1.0, -1.0, 1.0, 1.0])
    tr = np.vstack([calib.Tr_velo_to_cam, [0, 0, 0, 1]]) @ mirror_cloud
    return Calibration(mirror_image @ calib.P2, calib.R0_rect, tr[:3])


def test_flipped_image_and_cloud_stay_aligned(kitti_sample):
    frame = KittiDataset(kitti_sample).load_frame("000001")
    labels = frame.labels[frame.labels.names != "DontCare"]
    width, height = frame.image_size
    transform = ImageTransform(frame.image_size, frame.image_size, flipped=True)
    flipped_2d = transform.apply(labels.boxes_2d.xyxy)
    flipped_3d = CloudTransform(flipped=True).apply_boxes(labels.boxes_3d.data)
    projected = project_boxes_to_image(
        flipped_3d, flipped_calibration(frame.calib, width), (width, height)
    )
    # The projected flipped boxes fit the flipped 2D boxes as well as the originals fit.
    original = project_boxes_to_image(labels.boxes_3d.data, frame.calib, (width, height))
    assert (
        np.abs(projected - flipped_2d).max() <= np.abs(original - labels.boxes_2d.xyxy).max() + 2.0
    )
    assert pairwise_iou_2d(projected, flipped_2d).diagonal().min() > 0.8
    # And the flipped cloud still puts points in the flipped boxes.
    counts = points_in_boxes(flip_points(frame.points), flipped_3d).sum(axis=1)
    np.testing.assert_array_equal(
        counts, points_in_boxes(frame.points, labels.boxes_3d.data).sum(axis=1)
    )


def test_ema_schedule_and_arithmetic():
    assert ema_decay(0) == pytest.approx(0.99)
    assert ema_decay(100) == pytest.approx(0.995)
    assert ema_decay(1000) == pytest.approx(0.999)
    teacher, student = torch.nn.BatchNorm1d(2), torch.nn.BatchNorm1d(2)
    with torch.no_grad():
        teacher.weight.fill_(1.0)
        student.weight.fill_(3.0)
        teacher.running_mean.fill_(0.0)
        student.running_mean.fill_(10.0)
        student.num_batches_tracked.fill_(7)
    ema_update(teacher, student, 0.99)
    assert teacher.weight.tolist() == pytest.approx([1.02, 1.02])
    assert teacher.running_mean.tolist() == pytest.approx([0.1, 0.1])
    assert int(teacher.num_batches_tracked) == 7


def test_photometric_augmentation_changes_pixels_not_geometry():
    image = torch.rand(3, 48, 80) * 255
    out = strong_photometric(image, np.random.default_rng(3))
    assert out.shape == image.shape and torch.isfinite(out).all()
    assert not torch.allclose(out, image)
    again = strong_photometric(image, np.random.default_rng(3))
    assert torch.equal(out, again)


def test_torch_projection_matches_numpy(kitti_sample):
    calib = read_calib(KITTI_SAMPLE / "training" / "calib" / "000001.txt")
    boxes = random_boxes(np.random.default_rng(0), 30)
    boxes[:, 0] += 5
    xyxy, valid = project_boxes_torch(torch.from_numpy(boxes), calib, (1242, 375))
    expected = project_boxes_to_image(boxes, calib, (1242, 375))
    np.testing.assert_allclose(xyxy.numpy(), expected, atol=1e-6)
    assert valid.any() and not valid.all()
    a = torch.tensor([[0.0, 0, 2, 2], [0, 0, 2, 2]])
    b = torch.tensor([[1.0, 0, 3, 2], [4, 0, 6, 2]])
    assert giou_torch(a, b).tolist() == pytest.approx([2 / 6, -4 / 12], abs=1e-6)


# Pre-training long enough for the tiny detectors to see the frames' cars, then DetMatch with
# the same frames unlabeled, so that the two teachers agree on some objects.
SHORT_RUNS = (
    "train.steps=120", "train.eval_every=1000", "train.checkpoint_every=1000",
    "train.lr_2d=0.02", "train.lr_3d=0.004", "train.flip_probability=0.0",
    "ssl.unlabeled_split=train",
)  # fmt: skip


def train(config: ExperimentConfig, out: Path) -> list[dict]:
    """Train a run as `detmatch train` does; its metrics.jsonl step records."""
    trainer_type(config.ssl.method)(config, out, init_distributed("cpu")).run()
    lines = (out / "metrics.jsonl").read_text().splitlines()
    return [record for record in map(json.loads, lines) if "loss" in record]


@pytest.fixture(scope="module")
def detmatch_run(synth_root, tmp_path_factory):
    """run(steps, *overrides, preset=None) -> (step records, run directory) of a DetMatch run
    from one pre-training; each distinct run trains once per module."""
    base = apply_overrides(load_config(TINY), SHORT_RUNS).replace("data", root=str(synth_root))
    pretrained = tmp_path_factory.mktemp("pretrained")
    train(base, pretrained)
    runs: dict[tuple, tuple[list[dict], Path]] = {}

    def run(steps: int, *overrides: str, preset: str | None = None):
        key = (steps, overrides, preset)
        if key not in runs:
            config = apply_overrides(base, overrides)
            config = apply_preset(config, preset) if preset else config
            config = config.replace(
                "ssl", method="detmatch", pretrained=str(pretrained), steps=steps
            )
            out = tmp_path_factory.mktemp("detmatch")
            runs[key] = train(teacher_student_config(config), out), out
        return runs[key]

    run.pretrained = pretrained
    return run


def test_the_paper_preset_matches_pulls_and_moves_the_students(detmatch_run):
    """The paper's method: matched pseudo-labels in both modalities and the consistency loss;
    the students move, and the output teachers (their EMA) move less."""
    steps, out = detmatch_run(4, preset="paper")
    assert len(steps) == 4
    assert sum(r["pseudo_labels_3d"] for r in steps) > 0
    assert sum(r["pseudo_labels_2d"] for r in steps) > 0
    assert sum(r["consistency_pairs"] for r in steps) > 0
    before = load_checkpoint(list_checkpoints(detmatch_run.pretrained)[-1])
    after = load_checkpoint(list_checkpoints(out)[-1])
    for key in ("2d", "3d"):
        pretrained, student = before[f"model_{key}"], after[f"student_{key}"]
        assert any(not torch.equal(pretrained[k], student[k]) for k in pretrained)
        name = next(k for k in pretrained if k.endswith("weight"))
        student_shift = (student[name] - pretrained[name]).abs().sum()
        teacher_shift = (after[f"model_{key}"][name] - pretrained[name]).abs().sum()
        assert 0 < teacher_shift < student_shift


def test_the_defaults_learn_pseudo_labels_without_a_consistency_loss(detmatch_run):
    """What won on dev: the matching plus LiDAR-only labels, no consistency loss."""
    default, _ = detmatch_run(2)
    assert len(default) == 2 and sum(r["pseudo_labels_3d"] for r in default) > 0
    assert all(r["consistency_pairs"] == 0 and r["consistency"] == 0 for r in default)


def test_the_papers_rule_in_view_labels_only_matched_objects(detmatch_run):
    """tau_3d_unmatched 1.0: no LiDAR-only labels beside the defaults' same 2D labels, so no 2D
    ignore regions."""
    default, _ = detmatch_run(2)
    matched, _ = detmatch_run(2, "ssl.tau_3d_unmatched=1.0")
    assert matched[0]["pseudo_labels_2d"] == default[0]["pseudo_labels_2d"]  # the same teachers
    assert matched[0]["pseudo_labels_3d"] <= default[0]["pseudo_labels_3d"]
    assert all(r["ignored_2d"] == 0 for r in matched)


def test_lidar_only_labels_are_ignored_by_the_2d_student(detmatch_run):
    """LiDAR-only labels (a low score, so that the tiny teacher has some) add 3D labels, and
    their image projections are 2D ignore regions; the 2D labels stay the matched pairs."""
    matched, _ = detmatch_run(2, "ssl.tau_3d_unmatched=1.0")
    lidar_only, _ = detmatch_run(2, "ssl.tau_3d_unmatched=0.05")
    assert lidar_only[0]["pseudo_labels_2d"] == matched[0]["pseudo_labels_2d"]
    assert lidar_only[0]["pseudo_labels_3d"] >= matched[0]["pseudo_labels_3d"]
    assert sum(r["ignored_2d"] for r in lidar_only) > 0


def test_semi_supervised_methods_need_pretrained_weights(synth_root, tmp_path, capsys):
    args = ["train", "--config", str(TINY), "--data", str(synth_root), "--out", str(tmp_path / "r")]
    assert main([*args, "--method", "confidence"]) == 2
    assert "--pretrained" in capsys.readouterr().err


def test_confidence_run(synth_root, tmp_path):
    scheduled = tmp_path / "scheduled.toml"  # pre-training with schedules, as ssl_cpu's
    scheduled.write_text(
        TINY.read_text().replace(
            "[train]\n", '[train]\nschedule_2d = "step"\nschedule_3d = "onecycle"\n'
        )
    )
    args = ["train", "--config", str(scheduled), "--data", str(synth_root)]
    assert main([*args, "--out", str(tmp_path / "pre"), "--steps", "2"]) == 0
    assert main([*args, "--out", str(tmp_path / "conf"), "--steps", "2", "--method", "confidence",
                 "--pretrained", str(tmp_path / "pre")]) == 0  # fmt: skip
    config = json.loads((tmp_path / "conf" / "config.json").read_text())
    assert config["ssl"]["method"] == "confidence"
    assert load_config(TINY).ssl.tau_3d == 0.3 and load_config(TINY).ssl.tau_2d == 0.7
    # The run trained on the [ssl] stage's schedule, not pre-training's [train] one.
    pretraining = json.loads((tmp_path / "pre" / "config.json").read_text())["train"]
    train, ssl = config["train"], config["ssl"]
    assert (train["lr_2d"], train["lr_3d"]) == (ssl["lr_2d"], ssl["lr_3d"]) != (
        pretraining["lr_2d"], pretraining["lr_3d"]
    )  # fmt: skip
    assert train["warmup_steps"] == ssl["warmup_steps"] != pretraining["warmup_steps"]
    assert train["steps"] == ssl["steps"] == 2  # --steps: the stage's length
    assert train["schedule_2d"] == train["schedule_3d"] == "constant"
    assert (pretraining["schedule_2d"], pretraining["schedule_3d"]) == ("step", "onecycle")
