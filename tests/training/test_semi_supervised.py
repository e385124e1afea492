import json

import numpy as np
import pytest
import torch

from detmatch.cli import main
from detmatch.config import load_config
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
from detmatch.training.ema import ema_decay, ema_update
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


def test_short_detmatch_run_moves_students_and_matches(synth_root, tmp_path):
    """Pre-train the tiny detectors until they see the frames' cars, then run DetMatch with the
    same frames unlabeled: the teachers agree, pseudo-labels are matched, students move."""
    pretrain = tmp_path / "pretrain.toml"
    pretrain.write_text(
        TINY.read_text()
        .replace("[train]\nsteps = 6", "[train]\nsteps = 120")
        .replace("eval_every = 6", "eval_every = 1000")
        .replace("checkpoint_every = 3", "checkpoint_every = 1000")
        .replace("[train]\n", "[train]\nlr_2d = 0.02\nlr_3d = 0.004\nflip_probability = 0.0\n")
        .replace('unlabeled_split = "val"', 'unlabeled_split = "train"')
    )
    args = ["train", "--config", str(pretrain), "--data", str(synth_root)]
    assert main([*args, "--out", str(tmp_path / "pre")]) == 0
    # The paper's preset: matching and the consistency loss (off by default).
    assert main([*args, "--out", str(tmp_path / "ssl"), "--steps", "4", "--method", "detmatch",
                 "--pretrained", str(tmp_path / "pre"), "--preset", "paper"]) == 0  # fmt: skip
    records = [
        json.loads(line) for line in (tmp_path / "ssl" / "metrics.jsonl").read_text().splitlines()
    ]
    steps = [r for r in records if "pseudo_labels_3d" in r]
    assert len(steps) == 4
    assert (
        sum(r["pseudo_labels_3d"] for r in steps) > 0
        and sum(r["pseudo_labels_2d"] for r in steps) > 0
    )
    assert sum(r["consistency_pairs"] for r in steps) > 0
    from detmatch.checkpoints import list_checkpoints, load_checkpoint

    before = load_checkpoint(list_checkpoints(tmp_path / "pre")[-1])
    after = load_checkpoint(list_checkpoints(tmp_path / "ssl")[-1])
    for key in ("2d", "3d"):
        moved = [
            not torch.equal(before[f"model_{key}"][k], after[f"student_{key}"][k])
            for k in before[f"model_{key}"]
        ]
        assert any(moved)
        # The output (teacher) moved less than the student: an EMA of it.
        name = next(k for k in before[f"model_{key}"] if k.endswith("weight"))
        student_shift = (after[f"student_{key}"][name] - before[f"model_{key}"][name]).abs().sum()
        teacher_shift = (after[f"model_{key}"][name] - before[f"model_{key}"][name]).abs().sum()
        assert 0 < teacher_shift < student_shift

    # Diagnostics: the frames' own labels as the consistency targets (the unlabeled split is
    # labeled here): every confident projected candidate near a label is pulled.
    assert main([*args, "--out", str(tmp_path / "diagnostic"), "--steps", "2", "--method",
                 "detmatch", "--pretrained", str(tmp_path / "pre"), "--preset", "paper", "--set",
                 "ssl.consistency_targets=labels-projected"]) == 0  # fmt: skip
    lines = (tmp_path / "diagnostic" / "metrics.jsonl").read_text().splitlines()
    pairs = [json.loads(line)["consistency_pairs"] for line in lines if "consistency" in line]
    assert len(pairs) == 2 and sum(pairs) >= sum(r["consistency_pairs"] for r in steps[:2])

    def two_steps(name: str, *overrides: str) -> list[dict]:
        """The step records of a 2-step DetMatch run from the pre-training with --set overrides."""
        sets = [arg for override in overrides for arg in ("--set", override)]
        assert main([*args, "--out", str(tmp_path / name), "--steps", "2", "--method",
                     "detmatch", "--pretrained", str(tmp_path / "pre"), *sets]) == 0  # fmt: skip
        lines = (tmp_path / name / "metrics.jsonl").read_text().splitlines()
        return [json.loads(line) for line in lines if "pseudo_labels_3d" in line]

    # The defaults (what won on dev): the matching plus LiDAR-only labels above 0.6 whose
    # projections the 2D student does not learn as background; no consistency loss.
    default = two_steps("default")
    assert len(default) == 2 and sum(r["pseudo_labels_3d"] for r in default) > 0
    assert all(r["consistency_pairs"] == 0 and r["consistency"] == 0 for r in default)
    assert all(r["ignored_3d"] == 0 for r in default)

    # The paper's rule in view: only matched objects are labels; nothing is ignored.
    matched = two_steps("matched-only", "ssl.tau_3d_unmatched=1.0")
    assert matched[0]["pseudo_labels_2d"] == default[0]["pseudo_labels_2d"]  # the same teachers
    assert matched[0]["pseudo_labels_3d"] <= default[0]["pseudo_labels_3d"]
    assert all(r["ignored_3d"] == r["ignored_2d"] == 0 for r in matched)

    # Unmatched confident detections as ignore regions: the same labels, fewer negatives.
    ignore = two_steps(
        "ignore", "ssl.tau_3d_unmatched=1.0", "ssl.ignore_unmatched_score_3d=0.1",
        "ssl.ignore_unmatched_score_2d=0.1",
    )  # fmt: skip
    assert ignore[0]["pseudo_labels_3d"] == matched[0]["pseudo_labels_3d"]
    assert sum(r["ignored_3d"] + r["ignored_2d"] for r in ignore) > 0

    # LiDAR-only labels (a low score, so that the tiny teacher has some): their projections
    # are 2D ignore regions with the default lidar_only_ignore_2d, 2D background without it.
    protected = two_steps("protected", "ssl.tau_3d_unmatched=0.05")
    exposed = two_steps("exposed", "ssl.tau_3d_unmatched=0.05", "ssl.lidar_only_ignore_2d=false")
    assert protected[0]["pseudo_labels_2d"] == matched[0]["pseudo_labels_2d"]
    assert protected[0]["pseudo_labels_3d"] >= matched[0]["pseudo_labels_3d"]
    assert exposed[0]["pseudo_labels_3d"] == protected[0]["pseudo_labels_3d"]
    assert sum(r["ignored_2d"] for r in protected) > 0
    assert all(r["ignored_3d"] == 0 for r in protected)
    assert all(r["ignored_3d"] == r["ignored_2d"] == 0 for r in exposed)


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


def test_consistency_reductions_and_candidate_nms():
    from detmatch.training.consistency import _reduce, candidate_nms

    one, three = torch.tensor([1.0]), torch.tensor([2.0, 2.0, 5.0])
    assert _reduce([one, three], "pairs").item() == pytest.approx(10.0 / 4)
    assert _reduce([one, three], "frames").item() == pytest.approx((1.0 + 3.0) / 2)
    car = [15.0, 2.0, -0.9, 3.9, 1.6, 1.5, 0.2]
    shifted = [15.3, 2.1, -0.9, 3.9, 1.6, 1.5, 0.2]  # a duplicate peak of the same car
    apart = [15.0, -3.0, -0.9, 3.9, 1.6, 1.5, 0.2]  # beside it in 3D, overlapping in the image
    boxes = np.array([car, shifted, apart])
    projected = np.array([[100, 100, 200, 180], [102, 101, 203, 181], [150, 100, 250, 180]])
    rows = candidate_nms(boxes, projected.astype(float), np.array([0.6, 0.9, 0.5]))
    assert rows.tolist() == [1, 2]  # the best of the duplicates; the third survives both NMS
    projected[2] = [101, 100, 201, 180]  # now nearly the first's projection: 2D NMS drops it
    assert candidate_nms(boxes, projected.astype(float), np.array([0.6, 0.9, 0.5])).tolist() == [1]
