"""The gate of a retraining round: a checkpoint's models scored on the round's gate split with
the training code's evaluator, as `GateFigures` (moderate R40 AP per class and mAP, percent).
Candidate and parent are scored by the same function on the same frames; the promotion rule is
`serving.manifest.gate_passes`, which the manifest also checks its recorded decision against."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from detmatch.data.dataset import FrameDataset
from detmatch.models.build import load_detectors
from detmatch.training.evaluation import evaluate_detectors
from serving.manifest import GateFigures


def gate_figures(
    checkpoint: str | os.PathLike,
    data_root: str | os.PathLike,
    split: str,
    device: torch.device | None = None,
) -> GateFigures:
    """Both detectors of a checkpoint (file or run directory) on an ImageSets split of
    data_root, each with its own config's input size and pillar grid."""
    loaded = load_detectors(Path(checkpoint))
    config = loaded.config
    device = device or torch.device("cpu")
    model_2d, model_3d = loaded.model_2d.to(device), loaded.model_3d.to(device)
    classes = config.data.classes
    dataset = FrameDataset(data_root, split, classes, config.data.image_size, model_3d.grid)
    metrics = evaluate_detectors(
        model_2d, model_3d, dataset, classes,
        batch_size=config.train.batch_size, num_workers=config.data.num_workers,
    )  # fmt: skip
    return GateFigures(ap_2d=metrics["2d"], ap_3d=metrics["3d"], ap_bev=metrics["bev"])
