"""Loading trained detectors from a checkpoint and writing KITTI result files for a split."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from detmatch.config import ExperimentConfig, config_from_dict
from detmatch.data.dataset import FrameDataset, collate
from detmatch.data.kitti import write_objects
from detmatch.inference import detections_2d_to_objects, detections_3d_to_objects, predict_batch
from detmatch.models.detector2d import CenterNet2D
from detmatch.models.detector3d import PointPillars3D, pillar_grid
from detmatch.training.checkpoint import load_checkpoint, resolve_checkpoint


def load_detectors(
    checkpoint: Path,
) -> tuple[ExperimentConfig, CenterNet2D, PointPillars3D, dict[str, Any]]:
    """Config and both detectors (eval mode) from a checkpoint file or a run directory."""
    state = load_checkpoint(resolve_checkpoint(checkpoint))
    config = config_from_dict(state["config"])
    num_classes = len(config.data.classes)
    model_2d = CenterNet2D(config.detector2d, num_classes)
    model_3d = PointPillars3D(config.detector3d, num_classes)
    model_2d.load_state_dict(state["model_2d"])
    model_3d.load_state_dict(state["model_3d"])
    return config, model_2d.eval(), model_3d.eval(), state


def predict_split(
    checkpoint: Path, data_root: Path, split: str, out_dir: Path, batch_size: int = 4
) -> int:
    """Write OUT/3d/ID.txt (camera-frame boxes + projected 2D boxes) and OUT/2d/ID.txt (2D boxes
    with placeholder 3D fields) for every frame of the split. Returns the number of frames."""
    config, model_2d, model_3d, _ = load_detectors(checkpoint)
    classes = config.data.classes
    dataset = FrameDataset(
        data_root,
        split,
        classes,
        config.data.image_size,
        pillar_grid(config.detector3d),
        with_labels=False,
    )
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, collate_fn=collate)
    out_dir = Path(out_dir)
    with tqdm(total=len(dataset), desc=f"predict {split}", dynamic_ncols=True) as progress:
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
