"""Training samples: the 2D box source and moving batches between devices."""

import numpy as np
import pytest
import torch

from detmatch.config import ConfigError, DataConfig, load_config
from detmatch.data.dataset import FrameDataset, collate
from detmatch.data.unlabeled import UnlabeledDataset, collate_unlabeled
from detmatch.geometry import project_boxes_to_image
from detmatch.models.build import build_detectors
from tests.conftest import REPO

TINY = load_config(REPO / "configs" / "tiny.toml")


def frames(root, **options) -> FrameDataset:
    data = TINY.data
    grid = build_detectors(TINY)[1].grid
    return FrameDataset(root, "train", data.classes, data.image_size, grid, **options)


def test_projected_2d_boxes_are_the_3d_labels_projected(synth_root):
    annotated, projected = frames(synth_root), frames(synth_root, projected_2d=True)
    frame = annotated.kitti.load_frame(annotated.ids[0])
    a, p = annotated[0], projected[0]
    assert len(a.gt_3d) > 0
    np.testing.assert_array_equal(a.gt_3d.boxes, p.gt_3d.boxes)
    np.testing.assert_array_equal(a.gt_2d.classes, p.gt_2d.classes)
    expected = project_boxes_to_image(a.gt_3d.boxes, frame.calib, frame.image_size)
    np.testing.assert_allclose(p.gt_2d.boxes, p.image_transform.apply(expected), atol=1e-9)
    # The two sources differ (silhouettes vs projected box hulls) but describe the same objects.
    assert not np.allclose(a.gt_2d.boxes, p.gt_2d.boxes)
    assert np.abs(a.gt_2d.boxes - p.gt_2d.boxes).max() < 0.25 * a.image_transform.input_size[0]


def test_unknown_2d_box_source_is_a_config_error():
    with pytest.raises(ConfigError, match="train_boxes_2d"):
        DataConfig(train_boxes_2d="silhouette")


def test_batches_move_every_tensor_to_the_device(synth_root):
    dataset = frames(synth_root, augment=True)
    unlabeled = UnlabeledDataset(dataset, 0.5, (0.95, 1.05))
    batch = collate([dataset[0], dataset[1]]).to(torch.device("meta"))
    both = collate_unlabeled([unlabeled[0], unlabeled[1]]).to(torch.device("meta"))
    tensors = [batch.images, *batch.pillars.arrays, both.student_images, both.weak.images]
    tensors += [*both.student_pillars.arrays, *both.weak.pillars.arrays]
    assert all(t.device.type == "meta" for t in tensors)
    assert len(batch) == 2 and len(both) == 2 and batch.samples[0].frame_id == dataset.ids[0]
