"""Choosing frames without ImageSets: every frame or an ids file, from training/ or testing/,
PNG or JPEG images; clear errors for what is missing."""

import numpy as np
import pytest

from detmatch.data.kitti import KittiDataset, KittiFormatError, find_subset
from detmatch.data.selection import FrameSelection
from tests.stock_kitti import make_stock_kitti


@pytest.fixture
def stock(kitti_sample, tmp_path):
    return make_stock_kitti(kitti_sample, tmp_path / "kitti")


def test_subset_is_training_when_present_else_testing(stock, tmp_path):
    assert find_subset(stock) == "training"
    only_testing = tmp_path / "only_testing"
    only_testing.mkdir()
    (stock / "testing").rename(only_testing / "testing")
    assert find_subset(only_testing) == "testing"
    with pytest.raises(FileNotFoundError, match="neither training/ nor testing/"):
        find_subset(tmp_path)
    with pytest.raises(FileNotFoundError, match="looks like a subset directory itself"):
        find_subset(stock / "training")


def test_jpeg_and_png_frames_read_alike(stock, kitti_sample):
    dataset = KittiDataset(stock)
    assert dataset.ids() == ["000000", "000001", "000002"]
    assert dataset.image_path("000002").name == "000002.jpg"
    assert dataset.image_path("000001").name == "000001.png"
    original = KittiDataset(kitti_sample).load_frame("000002")
    frame = dataset.load_frame("000002")
    assert frame.image.shape == original.image.shape and frame.image.dtype == np.uint8
    difference = np.abs(frame.image.astype(int) - original.image.astype(int)).mean()
    assert difference < 4.0  # JPEG quality 95 of the same pixels
    assert len(frame.labels) == len(original.labels)
    testing = KittiDataset(stock, "testing")
    assert testing.ids() == ["000000", "000001"]
    assert testing.load_frame("000000").labels is None


def test_selections(stock, tmp_path):
    dataset, ids = FrameSelection(all_frames=True).resolve(stock)
    assert dataset.split_dir == "training" and ids == ["000000", "000001", "000002"]
    dataset, ids = FrameSelection(all_frames=True, subset="testing").resolve(stock)
    assert dataset.split_dir == "testing" and ids == ["000000", "000001"]
    ids_file = tmp_path / "ids.txt"
    ids_file.write_text("000002\n000000\n")
    assert FrameSelection(ids_file=ids_file).resolve(stock)[1] == ["000002", "000000"]
    (stock / "ImageSets").mkdir()
    (stock / "ImageSets" / "val.txt").write_text("000001\n")
    assert FrameSelection(split="val").resolve(stock)[1] == ["000001"]
    assert FrameSelection(split="val").describe() == "split 'val'"


def test_selection_errors_name_the_problem(stock, tmp_path):
    for bad in ({}, {"split": "val", "all_frames": True}):
        with pytest.raises(ValueError, match="exactly one of"):
            FrameSelection(**bad)
    with pytest.raises(ValueError, match="subset must be one of training, testing"):
        FrameSelection(all_frames=True, subset="validation")
    with pytest.raises(FileNotFoundError, match="no ImageSets/ .* --all .* --ids-file"):
        FrameSelection(split="val").resolve(stock)
    ids_file = tmp_path / "ids.txt"
    ids_file.write_text("000000\n000009\n")
    with pytest.raises(FileNotFoundError, match=r"3 frame files are missing: .*000009\.png"):
        FrameSelection(ids_file=ids_file).resolve(stock)
    (stock / "testing" / "velodyne" / "000001.bin").unlink()
    with pytest.raises(FileNotFoundError, match=r"testing/velodyne/000001\.bin"):
        FrameSelection(all_frames=True, subset="testing").resolve(stock)
    ids_file.write_text("\n")
    with pytest.raises(ValueError, match="the ids of .* has no frames"):
        FrameSelection(ids_file=ids_file).resolve(stock)
    (stock / "training" / "image_2" / "my frame.png").write_bytes(b"")
    with pytest.raises(KittiFormatError, match="invalid frame id 'my frame'"):
        FrameSelection(all_frames=True).resolve(stock)
