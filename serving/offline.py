"""Offline labeling: the labeler over a KITTI-layout data set (`detmatch label`), torch-free.

The frames are a `FrameSelection`: an ImageSets split, the ids of a file or every frame, of
training/ or testing/ (a stock KITTI download needs no ImageSets). For each frame it writes
    OUT/3d/ID.txt      KITTI result rows of the labels' 3D boxes whose centre projects into
                       the image (camera-frame box, projected 2D box, 3D class and score), as
                       `detmatch predict` writes 3D detections: `detmatch eval` scores both;
    OUT/2d/ID.txt      the matched labels' 2D boxes (2D class and score; KITTI's placeholder
                       3D fields);
    OUT/labels/ID.json every label with both boxes, classes, scores, its cost and provenance,
                       including LiDAR-only labels outside the camera's view (absent from the
                       KITTI files, which cover the camera's view only);
and OUT/labeling.json: model version, thresholds, the frames' source, counts and time. Files
are written atomically, so an interrupted run leaves whole files.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from detmatch.data.kitti import write_objects
from detmatch.data.selection import FrameSelection
from detmatch.files import atomic_write_bytes
from serving.labeler import Labeler
from serving.serialize import labels_to_json, labels_to_objects_2d, labels_to_objects_3d


@dataclass(frozen=True)
class LabelingSummary:
    frames: int
    labels: int
    matched: int
    lidar_only: int
    model_version: str
    seconds: float


def label_split(
    labeler: Labeler,
    data_root: str | os.PathLike,
    frames: FrameSelection | str,
    out_dir: str | os.PathLike,
    tau_hung: float | None = None,
    progress: bool = True,
) -> LabelingSummary:
    """Label the selected frames of a KITTI-layout data set into out_dir (see the module
    docstring); a string is an ImageSets split of training/."""
    if isinstance(frames, str):
        frames = FrameSelection(split=frames, subset="training")
    dataset, ids = frames.resolve(data_root)
    out_dir = Path(out_dir)
    start = time.perf_counter()
    labels = matched = 0
    thresholds: dict[str, float | None] = {}
    for frame_id in tqdm(ids, desc="label", dynamic_ncols=True, disable=not progress):
        frame = dataset.load_frame(frame_id, with_labels=False)
        result = labeler.label(frame.image, frame.points, frame.calib, tau_hung=tau_hung)
        write_objects(
            out_dir / "3d" / f"{frame_id}.txt",
            labels_to_objects_3d(result, frame.calib),
            decimals=4,
        )
        write_objects(out_dir / "2d" / f"{frame_id}.txt", labels_to_objects_2d(result), decimals=4)
        record = labels_to_json(frame_id, result)
        atomic_write_bytes(out_dir / "labels" / f"{frame_id}.json", json.dumps(record).encode())
        labels += len(result)
        matched += int(result.labels.matched.sum())
        thresholds = result.thresholds
    summary = LabelingSummary(
        frames=len(ids),
        labels=labels,
        matched=matched,
        lidar_only=labels - matched,
        model_version=labeler.version,
        seconds=round(time.perf_counter() - start, 3),
    )
    record = {
        **summary.__dict__,
        "model_path": str(labeler.path.resolve()),
        "data": str(Path(data_root).resolve()),
        "subset": dataset.split_dir,
        "frames_selected": frames.describe(),
        "split": frames.split,
        "thresholds": thresholds,
    }
    atomic_write_bytes(out_dir / "labeling.json", (json.dumps(record, indent=2) + "\n").encode())
    return summary
