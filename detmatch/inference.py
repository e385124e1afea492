"""Running both detectors on batches, turning their outputs into KITTI result rows, and
writing a checkpoint's result files for a selection of frames (`detmatch predict`)."""

from __future__ import annotations

from pathlib import Path

import torch
from tqdm import tqdm

from detmatch.data.dataset import Batch, FrameDataset, collate
from detmatch.data.kitti import KittiObjects, write_objects
from detmatch.data.results import result_objects_2d, result_objects_3d
from detmatch.data.selection import FrameSelection
from detmatch.models.build import load_detectors
from detmatch.models.contract import Detector2D, Detector3D, forward_pillars
from detmatch.precision import autocast, fp32
from detmatch.structures import Calibration, Detections


@torch.no_grad()
def predict_batch(
    model_2d: Detector2D,
    model_3d: Detector3D,
    batch: Batch,
    autocast_dtype: torch.dtype | None = None,
) -> list[tuple[Detections, Detections]]:
    """Both detectors on a batch, in eval mode; detections above each detector's score
    threshold, mapped back to the un-augmented frame (original pixels; LiDAR frame).
    autocast_dtype: the forward passes' precision (None: fp32, as deployed); decoding is fp32."""
    model_2d.eval()
    model_3d.eval()
    device = next(model_3d.parameters()).device
    batch = batch.to(device)
    with autocast(device, autocast_dtype):
        outputs_2d = fp32(model_2d(batch.images))
        outputs_3d = fp32(forward_pillars(model_3d, batch.pillars))
    frames_2d = model_2d.detect(outputs_2d)
    frames_3d = model_3d.detect(outputs_3d)
    return [
        (
            sample.image_transform.invert_detections(detections_2d),
            sample.cloud.invert_detections(detections_3d),
        )
        for sample, detections_2d, detections_3d in zip(
            batch.samples, frames_2d, frames_3d, strict=True
        )
    ]


def detections_2d_to_objects(detections: Detections, class_names: tuple[str, ...]) -> KittiObjects:
    """2D detections -> KITTI result rows with KITTI's placeholder 3D fields."""
    names = [class_names[c] for c in detections.classes]
    return result_objects_2d(detections.boxes, names, detections.scores)


def detections_3d_to_objects(
    detections: Detections,
    class_names: tuple[str, ...],
    calib: Calibration,
    image_size: tuple[int, int],
) -> KittiObjects:
    """3D detections whose centre is in the camera's view -> KITTI result rows."""
    names = [class_names[c] for c in detections.classes]
    return result_objects_3d(detections.boxes, names, detections.scores, calib, image_size)


def predict_split(
    checkpoint: Path,
    data_root: Path,
    frames: FrameSelection | str,
    out_dir: Path,
    batch_size: int = 4,
) -> int:
    """Write OUT/3d/ID.txt (camera-frame boxes + projected 2D boxes) and OUT/2d/ID.txt (2D boxes
    with placeholder 3D fields) for every selected frame (a string is an ImageSets split of
    training/). Returns the number of frames."""
    if isinstance(frames, str):
        frames = FrameSelection(split=frames, subset="training")
    loaded = load_detectors(checkpoint)
    config, model_2d, model_3d = loaded.config, loaded.model_2d, loaded.model_3d
    classes = config.data.classes
    dataset = FrameDataset(
        data_root, frames, classes, config.data.image_size, model_3d.grid, with_labels=False
    )
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, collate_fn=collate)
    out_dir = Path(out_dir)
    with tqdm(total=len(dataset), desc="predict", dynamic_ncols=True) as progress:
        for batch in loader:
            for sample, (detections_2d, detections_3d) in zip(
                batch.samples, predict_batch(model_2d, model_3d, batch), strict=True
            ):
                objects_3d = detections_3d_to_objects(
                    detections_3d, classes, sample.calib, sample.image_transform.original_size
                )
                write_objects(out_dir / "3d" / f"{sample.frame_id}.txt", objects_3d, decimals=4)
                objects_2d = detections_2d_to_objects(detections_2d, classes)
                write_objects(out_dir / "2d" / f"{sample.frame_id}.txt", objects_2d, decimals=4)
            progress.update(len(batch))
    return len(dataset)
