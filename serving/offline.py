"""Offline labeling: the labeler over a KITTI-layout data set (`detmatch label`), torch-free.

For each frame of the split it writes
    OUT/3d/ID.txt      KITTI result rows of the labels' 3D boxes whose centre projects into
                       the image (camera-frame box, projected 2D box, 3D class and score), as
                       `detmatch predict` writes 3D detections: `detmatch eval` scores both;
    OUT/2d/ID.txt      the matched labels' 2D boxes (2D class and score; KITTI's placeholder
                       3D fields);
    OUT/labels/ID.json every label with both boxes, classes, scores, its cost and provenance,
                       including LiDAR-only labels outside the camera's view (absent from the
                       KITTI files, which cover the camera's view only);
and OUT/labeling.json: model version, thresholds, counts and time. Files are written
atomically, so an interrupted run leaves whole files.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from detmatch.data.kitti import KittiDataset, KittiObjects, atomic_write_bytes, write_objects
from detmatch.data.results import result_objects_2d, result_objects_3d
from detmatch.pseudo_labels import Provenance
from detmatch.structures import Calibration
from serving.labeler import FrameLabels, Labeler

PROVENANCE_NAMES = {
    Provenance.MATCHED: "matched",
    Provenance.LIDAR_ONLY_OUTSIDE_VIEW: "lidar_only_outside_view",
}


def labels_to_objects_3d(result: FrameLabels, calib: Calibration) -> KittiObjects:
    """Labels whose 3D box centre projects into the image -> KITTI result rows (camera-frame
    box, projected 2D box, alpha; the 3D class and score)."""
    labels = result.labels
    names = [result.classes[c] for c in labels.class_3d]
    return result_objects_3d(labels.boxes_3d, names, labels.score_3d, calib, result.image_size)


def labels_to_objects_2d(result: FrameLabels) -> KittiObjects:
    """Matched labels' 2D boxes -> KITTI result rows with KITTI's placeholder 3D fields."""
    labels = result.labels
    keep = labels.matched
    names = [result.classes[c] for c in labels.class_2d[keep]]
    return result_objects_2d(labels.boxes_2d[keep], names, labels.score_2d[keep])


def labels_to_json(frame_id: str, result: FrameLabels) -> dict[str, Any]:
    """Every label of a frame, JSON-ready (NaN fields of absent boxes become null)."""
    labels = result.labels

    def number(value: float) -> float | None:
        return None if not math.isfinite(value) else round(float(value), 6)

    rows = []
    for i in range(len(labels)):
        matched = labels.provenance[i] == Provenance.MATCHED
        rows.append(
            {
                "provenance": PROVENANCE_NAMES[Provenance(int(labels.provenance[i]))],
                "class_3d": result.classes[labels.class_3d[i]],
                "class_2d": result.classes[labels.class_2d[i]] if matched else None,
                "box_3d": [number(v) for v in labels.boxes_3d[i]],
                "box_2d": [number(v) for v in labels.boxes_2d[i]] if matched else None,
                "score_3d": number(labels.score_3d[i]),
                "score_2d": number(labels.score_2d[i]),
                "cost": number(labels.cost[i]),
            }
        )
    return {
        "frame_id": frame_id,
        "model_version": result.model_version,
        "image_size": list(result.image_size),
        "thresholds": result.thresholds,
        "box_3d": "LiDAR frame x y z l w h yaw, gravity centre",
        "box_2d": "x1 y1 x2 y2 pixels",
        "labels": rows,
    }


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
    split: str,
    out_dir: str | os.PathLike,
    tau_hung: float | None = None,
    progress: bool = True,
) -> LabelingSummary:
    """Label every frame of a KITTI-layout split into out_dir (see the module docstring)."""
    dataset = KittiDataset(data_root)
    ids = dataset.ids(split)
    if not ids:
        raise ValueError(f"split {split!r} of {data_root} has no frames")
    out_dir = Path(out_dir)
    start = time.perf_counter()
    labels = matched = 0
    thresholds: dict[str, float | None] = {}
    for frame_id in tqdm(ids, desc=f"label {split}", dynamic_ncols=True, disable=not progress):
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
        "split": split,
        "thresholds": thresholds,
    }
    atomic_write_bytes(out_dir / "labeling.json", (json.dumps(record, indent=2) + "\n").encode())
    return summary
