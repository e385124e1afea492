"""What the label store's tests share: labels of a KITTI sample frame from the served model,
a put of them, and the files of a store's shards against those its index lists."""

from __future__ import annotations

from pathlib import Path

from detmatch.data.kitti import KittiDataset
from serving.store import LabelStore, list_frames
from tests.conftest import KITTI_SAMPLE

# The test model's scores are all below the manifest's thresholds: these make it label.
LABEL_EVERYTHING = {"score_threshold_2d": 0.01, "score_threshold_3d": 0.01, "tau_hung": 10.0}


def labels_of(labeler, source: str = "000000"):
    """(PNG bytes, frame, labels) of a KITTI sample frame."""
    dataset = KittiDataset(KITTI_SAMPLE)
    frame = dataset.load_frame(source, with_labels=False)
    result = labeler.label(frame.image, frame.points, frame.calib, **LABEL_EVERYTHING)
    return dataset.image_path(source).read_bytes(), frame, result


def put_frame(store: LabelStore, labeler, frame_id: str, source: str = "000000", **kwargs):
    png, frame, result = labels_of(labeler, source)
    return store.put(frame_id, png, frame.points, frame.calib, result, **kwargs)


def shard_files(root: Path) -> set[str]:
    """Every file of the store's shards but the index and the lock."""
    return {
        p.relative_to(root).as_posix()
        for p in root.rglob("*")
        if p.is_file() and "index.sqlite" not in p.name and p.name != ".lock"
    }


def listed_files(root: Path) -> set[str]:
    """Every file the store's index lists, as shard_files names them."""
    return {
        f"shards/{r.shard}/{relative}" for r in list_frames(root) for relative in r.files
    }  # fmt: skip
