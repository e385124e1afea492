"""Labeled-frame augmentation: ground-truth database sampling, global rotation and scale, the
2D multi-scale window, repeat-factor sampling and the learning-rate schedules."""

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from detmatch.config import AugmentConfig, load_config
from detmatch.data.dataset import FrameDataset, ImageTransform, image_to_tensor
from detmatch.data.gt_sampling import GroundTruthDatabase
from detmatch.data.kitti import KittiDataset
from detmatch.geometry import pairwise_intersection_2d, pairwise_iou_bev, points_in_boxes
from detmatch.models.build import build_detectors
from detmatch.training.distributed import StepSampler, repeat_factors
from detmatch.training.trainer import learning_rates
from tests.conftest import REPO

TINY = load_config(REPO / "configs" / "tiny.toml")
GRID = build_detectors(TINY)[1].grid
NO_AUGMENT = AugmentConfig(gt_sampling=False, rotation=0.0, scale=(1.0, 1.0))


def labeled(root, split="train", flip=0.0, **options) -> FrameDataset:
    augment = dataclasses.replace(NO_AUGMENT, **options)
    data = TINY.data
    return FrameDataset(root, split, data.classes, data.image_size, GRID, augment=True,
                        flip_probability=flip, labeled_augment=augment)  # fmt: skip


def test_ground_truth_sampling_pastes_whole_objects_without_overlap(synth_root):
    plain = labeled(synth_root)
    sampled = labeled(synth_root, gt_sampling=True, gt_sample_counts=(12, 8, 8), gt_min_points=3)
    assert sampled.database.frame_ids <= set(sampled.ids) and len(sampled.database) > 0
    pasted_total = 0
    for index in range(len(sampled)):
        before, after = plain[(index, 7)], sampled[(index, 7)]
        # The image and the 2D targets are untouched; the 3D targets grow by the pasted objects.
        assert torch.equal(before.image, after.image)
        np.testing.assert_array_equal(before.gt_2d.boxes, after.gt_2d.boxes)
        np.testing.assert_array_equal(after.gt_3d.boxes[: len(before.gt_3d)], before.gt_3d.boxes)
        pasted = after.gt_3d.boxes[len(before.gt_3d) :]
        pasted_total += len(pasted)
        # No two boxes of the frame overlap in bird's-eye view where a pasted one is involved.
        iou = pairwise_iou_bev(after.gt_3d.boxes, after.gt_3d.boxes)
        np.fill_diagonal(iou, 0.0)
        assert iou[len(before.gt_3d) :].max(initial=0.0) == 0.0
        # The points inside a pasted box are exactly its database object's points.
        objects = {tuple(np.round(o.box, 6)): o for o in sampled.database.objects}
        for box in pasted:
            source = objects[tuple(np.round(box, 6))]
            assert source.frame_id != after.frame_id
            inside = after.points[points_in_boxes(after.points, box[None])[0]]
            assert {tuple(p) for p in inside} == {tuple(p) for p in source.points}
    assert pasted_total > 0
    # Deterministic per (seed, draw); other draws paste other objects.
    np.testing.assert_array_equal(sampled[(1, 3)].points, sampled[(1, 3)].points)
    pasted_sets = {tuple(np.round(sampled[(0, d)].gt_3d.boxes[:, 0], 3)) for d in range(10)}
    assert len(pasted_sets) > 1


def test_the_database_holds_only_the_split_it_was_built_from(synth_root):
    kitti = KittiDataset(synth_root)
    val_ids = kitti.ids("val")
    database = GroundTruthDatabase.build(kitti, val_ids, TINY.data.classes, 1)
    assert database.frame_ids and database.frame_ids <= set(val_ids)
    assert not database.frame_ids & set(kitti.ids("train"))


def test_rotation_and_scale_keep_points_and_boxes_aligned(synth_root):
    plain = labeled(synth_root)
    turned = labeled(synth_root, rotation=0.7, scale=(0.9, 1.1), flip=0.5)
    for draw in range(4):
        before, after = plain[(0, draw)], turned[(0, draw)]
        assert after.cloud.rotation != 0.0 and after.cloud.scale != 1.0
        counts = points_in_boxes(before.points, before.gt_3d.boxes).sum(axis=1)
        moved = points_in_boxes(after.points, after.gt_3d.boxes).sum(axis=1)
        np.testing.assert_array_equal(moved, counts)
        back = after.cloud.invert_boxes(after.gt_3d.boxes)
        np.testing.assert_allclose(back[:, :6], before.gt_3d.boxes[:, :6], atol=1e-4)
        # The camera view used for the 3D targets follows the cloud: background is learned
        # where the un-augmented cells are in view.
        grid_xy = np.array([[20.0, 0.0], [5.0, 30.0]])
        expected = before.camera_view.contains_bev(grid_xy)
        points = np.column_stack([grid_xy, np.zeros(2)])
        assert (after.camera_view.contains_bev(after.cloud.apply_points(points)[:, :2])
                == expected).all()  # fmt: skip


def test_the_multi_scale_window_keeps_image_and_boxes_aligned(synth_root):
    """A white square on black, through flip, rescale and a cropped or padded window: the
    square's box mapped by the transform is white in the window and its surroundings black."""
    original = np.zeros((100, 200, 3), dtype=np.uint8)
    original[30:70, 60:100] = 255
    box = np.array([[60.0, 30.0, 100.0, 70.0]])
    size = TINY.data.image_size
    for resized, offset in (((480, 144), (60, 20)), ((256, 80), (-20, -6))):
        window = ImageTransform((200, 100), size, True, resized, offset)
        image = image_to_tensor(original, window)
        assert image.shape == (3, size[1], size[0])
        np.testing.assert_allclose(window.invert(window.apply(box)), box, atol=1e-9)
        x1, y1, x2, y2 = np.round(window.apply(box)[0]).astype(int)
        assert image[:, y1 + 2 : y2 - 2, x1 + 2 : x2 - 2].min() > 250
        ring = image[:, max(y1 - 6, 0) : y2 + 6, max(x1 - 6, 0) : x2 + 6].clone()
        ring[:, 8 : 8 + (y2 - y1) - 4, 8 : 8 + (x2 - x1) - 4] = 0
        assert ring.mean() < 0.5 * image[:, y1:y2, x1:x2].mean()
    sample = labeled(synth_root, image_scale=(0.6, 1.4))[(0, 5)]
    assert sample.image.shape == (3, size[1], size[0])
    boxes = sample.gt_2d.boxes
    assert (boxes[:, 0] >= 0).all() and (boxes[:, 2] <= size[0]).all()
    assert (boxes[:, 1] >= 0).all() and (boxes[:, 3] <= size[1]).all()


def test_repeat_factor_sampling_draws_rare_frames_more_often():
    presence = np.array([[1, 0, 0]] * 18 + [[1, 1, 0], [0, 0, 1]], dtype=bool)
    factors = repeat_factors(presence, 0.3)
    assert factors[:18] == pytest.approx(1.0) and factors[18] == pytest.approx(np.sqrt(6))
    sampler = StepSampler(20, 4, seed=0, start_step=0, repeat_factors=factors)
    stream = iter(sampler)
    counts = np.bincount([next(stream)[0] for _ in range(4000)], minlength=20)
    assert counts[18] > 2 * counts[:18].mean() and counts[19] > 2 * counts[:18].mean()
    # A resumed sampler replays the same frames.
    resumed = iter(StepSampler(20, 4, seed=0, start_step=250, repeat_factors=factors))
    replay = iter(StepSampler(20, 4, seed=0, start_step=0, repeat_factors=factors))
    for _ in range(1000):
        next(replay)
    assert [next(resumed) for _ in range(8)] == [next(replay) for _ in range(8)]


def test_learning_rate_schedules():
    train = dataclasses.replace(
        TINY.train, steps=900, warmup_steps=10, lr_2d=0.02, lr_3d=0.003, schedule_2d="step",
        milestones_2d=(0.5, 0.8), schedule_3d="onecycle", onecycle_peak=0.4, onecycle_div=10.0,
    )  # fmt: skip
    assert learning_rates(train, 4)[0] == pytest.approx(0.02 * 0.5)  # warm-up
    assert learning_rates(train, 449)[0] == pytest.approx(0.02)
    assert learning_rates(train, 450)[0] == pytest.approx(0.002)
    assert learning_rates(train, 720)[0] == pytest.approx(0.0002)
    assert learning_rates(train, 0)[1] == pytest.approx(0.0003)
    assert learning_rates(train, 360)[1] == pytest.approx(0.003)
    assert learning_rates(train, 900)[1] == pytest.approx(0.003 / 10 / 1e4)
    rates = [learning_rates(train, s)[1] for s in range(0, 900, 10)]
    assert max(rates) == pytest.approx(0.003, rel=1e-3) and np.argmax(rates) == 36


def test_pasting_image_crops_adds_the_objects_to_both_detectors(synth_root):
    """With gt_sampling_image, a pasted object's crop lands at its 2D box in the image (the
    rig is the same in every frame) and its box joins the 2D targets; no pasted 2D box touches
    another box of the frame. The cloud gets the same pasted objects as without images: one
    whose 2D box would touch another is pasted into the cloud only."""
    plain = labeled(synth_root, gt_sampling=True, gt_sample_counts=(0, 6, 6), gt_min_points=1)
    joint = labeled(synth_root, gt_sampling=True, gt_sample_counts=(0, 6, 6), gt_min_points=1,
                    gt_sampling_image=True)  # fmt: skip
    assert all(o.crop is not None for o in joint.database.objects)
    grown_2d = grown_3d = 0
    for index in range(len(joint)):
        sample, without = joint[(index, 11)], plain[(index, 11)]
        frame = joint.kitti.load_frame(joint.ids[index])
        kept = int(np.isin(frame.labels.names, TINY.data.classes).sum())
        np.testing.assert_array_equal(sample.gt_3d.boxes, without.gt_3d.boxes)
        np.testing.assert_array_equal(sample.points, without.points)
        pasted_2d, pasted_3d = len(sample.gt_2d) - kept, len(sample.gt_3d) - kept
        assert 0 <= pasted_2d <= pasted_3d
        grown_2d, grown_3d = grown_2d + pasted_2d, grown_3d + pasted_3d
        if pasted_2d:
            new = sample.gt_2d.boxes[kept:]
            old = sample.image_transform.apply(frame.labels.boxes_2d.xyxy)
            assert pairwise_intersection_2d(new, old).max() == 0
            touching = pairwise_intersection_2d(new, new) > 0
            assert not (touching & ~np.eye(len(new), dtype=bool)).any()
            assert not torch.equal(sample.image, without.image)
        else:
            assert torch.equal(sample.image, without.image)
    assert 0 < grown_2d < grown_3d  # some crops collided: those objects went to the cloud only


def test_an_object_without_pixels_stays_in_the_database_for_the_cloud(synth_root, tmp_path):
    """An object whose 2D box rounds to nothing has no crop to paste, but the database with
    images keeps it for the cloud: it holds the same objects as the one without images, so
    the 3D detector's pastes and random draws are the same either way."""
    root = Path(shutil.copytree(synth_root, tmp_path / "synth"))
    kitti = KittiDataset(root)
    frame_id = kitti.ids("train")[0]
    label_file = root / "training" / "label_2" / f"{frame_id}.txt"
    lines = label_file.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.split()[0] in TINY.data.classes)
    fields = lines[first].split()
    fields[4:8] = ["100.2", "50.0", "100.4", "80.0"]  # a sliver: rounds to zero width
    lines[first] = " ".join(fields)
    label_file.write_text("\n".join(lines) + "\n")
    ids = kitti.ids("train")
    plain = GroundTruthDatabase.build(kitti, ids, TINY.data.classes, 1)
    joint = GroundTruthDatabase.build(kitti, ids, TINY.data.classes, 1, with_images=True)
    assert [(o.frame_id, o.box.tolist()) for o in joint.objects] == [
        (o.frame_id, o.box.tolist()) for o in plain.objects
    ]
    sliver = [o for o in joint.objects if o.frame_id == frame_id and o.crop is None]
    assert len(sliver) == 1
    assert all(o.crop is not None for o in joint.objects if o is not sliver[0])
    # Drawn into the other frames, it is pasted into the cloud and never carries a crop.
    drawn = 0
    for other in ids[1:]:
        labels = kitti.load_frame(other).labels
        for seed in range(20):
            args = (labels.boxes_3d.data, np.zeros(len(labels), int), (30, 30, 30), other)
            with_2d = joint.sample(np.random.default_rng(seed), *args, labels.boxes_2d.xyxy)
            without = plain.sample(np.random.default_rng(seed), *args)
            assert [o.box.tolist() for o in with_2d] == [o.box.tolist() for o in without]
            slivers = [o for o in with_2d if np.array_equal(o.box, sliver[0].box)]
            assert all(o.crop is None for o in slivers)
            drawn += len(slivers)
    assert drawn > 0
