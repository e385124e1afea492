"""The manifest of a model version: everything a server needs to run the two graphs the way
training ran the detectors, and where they came from."""

from __future__ import annotations

import math
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime
import scipy
import torch

import detmatch
from detmatch.config import ExperimentConfig, config_to_dict
from detmatch.constants import IMAGE_MEAN, IMAGE_STD
from detmatch.files import sha256_file
from detmatch.matching_policy import MatchingPolicy
from detmatch.models.pillars import PillarGrid
from export.graphs import EXPORTER, io_spec, opset_of
from export.parity import ParityReport
from serving.manifest import (
    MANIFEST_FORMAT,
    ImagePreprocessing,
    Manifest,
    MatchingSpec,
    Model2DSpec,
    Model3DSpec,
    Models,
    PillarGridSpec,
    PillarPreprocessing,
    Postprocessing,
    RetrainingRecord,
    TrainingRecord,
)
from serving.repository import MODEL_2D_FILE, MODEL_3D_FILE, file_record


def tool_versions() -> dict[str, str]:
    return {
        "python": platform.python_version(),
        "detmatch": detmatch.__version__,
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "exporter": EXPORTER,
    }


def build_manifest(
    version: str,
    staging: Path,
    config: ExperimentConfig,
    checkpoint: dict[str, Any],
    checkpoint_file: Path,
    parity: ParityReport,
    exported_at: float,
    grid: PillarGrid,
    checkpoint_copy: str | None = None,
    retraining: RetrainingRecord | None = None,
) -> Manifest:
    """The manifest of the version whose files are in `staging`; grid: the 3D detector's;
    checkpoint_copy: the name of the checkpoint's copy in `staging` (None: not kept);
    retraining: the record of the retraining round that made the version."""
    detector2d, detector3d = config.detector2d, config.detector3d
    path_2d, path_3d = staging / MODEL_2D_FILE, staging / MODEL_3D_FILE
    plain_config = config_to_dict(config)
    return Manifest(
        format=MANIFEST_FORMAT,
        version=version,
        exported_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(exported_at)),
        classes=tuple(config.data.classes),
        models=Models(
            detector2d=Model2DSpec(
                file=MODEL_2D_FILE,
                opset=opset_of(path_2d),
                **io_spec(path_2d),
                preprocessing=ImagePreprocessing(
                    in_graph=True,
                    input="the original image: (height, width, 3) uint8 RGB, any size",
                    steps=(
                        "cast to float32 in [0, 255], HWC -> 1CHW",
                        "Resize linear, coordinate_transformation_mode half_pixel, to "
                        "input_size (torch F.interpolate bilinear, align_corners=False, no "
                        "antialias: training's image_to_tensor)",
                        "(x - mean * 255) / (std * 255) per channel",
                    ),
                    input_size=tuple(config.data.image_size),
                    mean=IMAGE_MEAN,
                    std=IMAGE_STD,
                ),
                postprocessing=Postprocessing(
                    in_graph="3x3 max-pool peaks, top-k, boxes scaled to the original image",
                    boxes="xyxy pixels of the original image",
                    outside_graph="keep scores > score_threshold",
                ),
                max_detections=detector2d.max_detections,
                score_threshold=detector2d.score_threshold,
            ),
            detector3d=Model3DSpec(
                file=MODEL_3D_FILE,
                opset=opset_of(path_3d),
                **io_spec(path_3d),
                preprocessing=PillarPreprocessing(
                    in_graph=False,
                    input="LiDAR points: (N, 4) float32 x, y, z, intensity, LiDAR frame",
                    function="detmatch.models.pillars.pillarize(points, grid)",
                    grid=PillarGridSpec.of(grid),
                ),
                postprocessing=Postprocessing(
                    in_graph="3x3 max-pool peaks, top-k, box regression decoded",
                    boxes="LiDAR frame x y z l w h yaw, gravity centre, metres / radians",
                    outside_graph="keep scores > score_threshold",
                ),
                max_detections=detector3d.max_detections,
                score_threshold=detector3d.score_threshold,
            ),
        ),
        matching=MatchingSpec.of(MatchingPolicy.from_config(config.ssl)),
        training=TrainingRecord(
            checkpoint=str(checkpoint_file.resolve()),
            checkpoint_sha256=sha256_file(checkpoint_file),
            step=int(checkpoint.get("step", -1)),
            data=plain_config["data"],
            config=plain_config,
            metrics=_json_safe(checkpoint.get("metrics", {})),
            checkpoint_file=checkpoint_copy,
        ),
        parity=_json_safe(parity.to_json()),
        tools=tool_versions(),
        files={name: file_record(staging / name) for name in (MODEL_2D_FILE, MODEL_3D_FILE)},
        retraining=retraining,
    )


def _json_safe(value: Any) -> Any:
    """Checkpoint metrics as plain JSON (tensors and numpy scalars to numbers; NaN to None)."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, torch.Tensor):
        return _json_safe(value.tolist())
    if isinstance(value, bool | str) or value is None:
        return value
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    return str(value)
