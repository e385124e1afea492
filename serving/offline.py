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

With a `LabelStore` (`detmatch label --store DIR`) every frame and its labels are also stored,
exactly as the service stores a labeled frame (the image as PNG: a JPEG is re-encoded), so
batch labeling feeds retraining like the service does; out_dir may then be None.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from detmatch.data.kitti import format_objects
from detmatch.data.selection import FrameSelection
from detmatch.files import atomic_write_bytes
from detmatch.structures import Calibration
from serving.labeler import FrameLabels, Labeler
from serving.png import encode_png
from serving.serialize import labels_to_json, labels_to_objects_2d, labels_to_objects_3d
from serving.store import DEFAULT_NAMESPACE, LabelStore, StoreOutcome


@dataclass(frozen=True)
class LabelingSummary:
    frames: int
    labels: int
    matched: int
    lidar_only: int
    model_version: str
    seconds: float
    stored: int = 0  # frames newly written into the label store
    already_stored: int = 0  # frames the store held already (left as they were)


def label_split(
    labeler: Labeler,
    data_root: str | os.PathLike,
    frames: FrameSelection | str,
    out_dir: str | os.PathLike | None,
    tau_hung: float | None = None,
    progress: bool = True,
    store: LabelStore | None = None,
    namespace: str = DEFAULT_NAMESPACE,
) -> LabelingSummary:
    """Label the selected frames of a KITTI-layout data set into out_dir and/or store (see the
    module docstring); a string is an ImageSets split of training/."""
    if isinstance(frames, str):
        frames = FrameSelection(split=frames, subset="training")
    if out_dir is None and store is None:
        raise ValueError("label_split needs an output directory, a label store or both")
    dataset, ids = frames.resolve(data_root)
    out = None if out_dir is None else Path(out_dir)
    start = time.perf_counter()
    labels = matched = stored = 0
    thresholds: dict[str, float | None] = {}
    for frame_id in tqdm(ids, desc="label", dynamic_ncols=True, disable=not progress):
        frame = dataset.load_frame(frame_id, with_labels=False)
        result = labeler.label(frame.image, frame.points, frame.calib, tau_hung=tau_hung)
        labels += len(result)
        matched += int(result.labels.matched.sum())
        thresholds = result.thresholds
        if store is not None:
            png = image_png(dataset.image_path(frame_id), frame.image)
            put = store.put(frame_id, png, frame.points, frame.calib, result, namespace)
            stored += put.outcome != StoreOutcome.UNCHANGED
        if out is None:
            continue
        for relative, data in result_files(frame_id, result, frame.calib).items():
            atomic_write_bytes(out / relative, data)
    summary = LabelingSummary(
        frames=len(ids),
        labels=labels,
        matched=matched,
        lidar_only=labels - matched,
        model_version=labeler.version,
        seconds=round(time.perf_counter() - start, 3),
        stored=stored,
        already_stored=len(ids) - stored if store is not None else 0,
    )
    if out is None:
        return summary
    record = labeling_record(
        summary, labeler.path, str(Path(data_root).resolve()), dataset.split_dir, frames,
        thresholds, store,
    )  # fmt: skip
    atomic_write_bytes(out / "labeling.json", (json.dumps(record, indent=2) + "\n").encode())
    return summary


def result_files(frame_id: str, result: FrameLabels, calib: Calibration) -> dict[str, bytes]:
    """The bytes of a frame's result files by path relative to the output directory (3d/ID.txt,
    2d/ID.txt, labels/ID.json; see the module docstring): what every labeling engine writes."""
    return {
        f"3d/{frame_id}.txt": format_objects(
            labels_to_objects_3d(result, calib), decimals=4
        ).encode(),
        f"2d/{frame_id}.txt": format_objects(labels_to_objects_2d(result), decimals=4).encode(),
        f"labels/{frame_id}.json": json.dumps(labels_to_json(frame_id, result)).encode(),
    }


def labeling_record(
    summary: LabelingSummary,
    model_path: Path,
    data: str,
    subset: str,
    frames: FrameSelection,
    thresholds: dict[str, float | None],
    store: LabelStore | None,
) -> dict:
    """OUT/labeling.json's fields: the summary, the model, the frames' source and the store."""
    return {
        **summary.__dict__,
        "model_path": str(model_path.resolve()),
        "data": data,
        "subset": subset,
        "frames_selected": frames.describe(),
        "split": frames.split,
        "thresholds": thresholds,
        "store": None
        if store is None
        else {"root": str(store.root.resolve()), "shard": store.shard},
    }


def image_png(path: Path, pixels: np.ndarray) -> bytes:
    """What the store keeps of a frame's image file: a PNG as it is, any other image (JPEG)
    re-encoded as PNG from its decoded (H, W, 3) uint8 RGB pixels."""
    return path.read_bytes() if path.suffix.lower() == ".png" else encode_png(pixels)
