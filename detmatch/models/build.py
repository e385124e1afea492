"""The only places that construct detectors: from a config, or from a checkpoint.

`[detector2d] type` and `[detector3d] type` name a class in the mappings below. Adding a
detector is a class that implements `detmatch.models.contract` plus one line here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from detmatch.checkpoints import load_checkpoint, resolve_checkpoint
from detmatch.config import ConfigError, ExperimentConfig, config_from_dict
from detmatch.models.contract import Detector2D, Detector3D
from detmatch.models.detector2d import CenterNet2D
from detmatch.models.detector3d import PointPillars3D

DETECTORS_2D: dict[str, type[Detector2D]] = {"centernet": CenterNet2D}
DETECTORS_3D: dict[str, type[Detector3D]] = {"pointpillars": PointPillars3D}


def _detector_class(mapping: dict[str, type], section: str, name: str) -> type:
    if name not in mapping:
        raise ConfigError(
            f"[{section}] type must be one of {', '.join(sorted(mapping))}, got {name!r}"
        )
    return mapping[name]


def build_detectors(config: ExperimentConfig) -> tuple[Detector2D, Detector3D]:
    """Both detectors with fresh weights, for the config's classes."""
    num_classes = len(config.data.classes)
    type_2d = _detector_class(DETECTORS_2D, "detector2d", config.detector2d.type)
    type_3d = _detector_class(DETECTORS_3D, "detector3d", config.detector3d.type)
    return type_2d(config.detector2d, num_classes), type_3d(config.detector3d, num_classes)


@dataclass
class LoadedDetectors:
    """A checkpoint's config, its output models (eval mode) and the checkpoint itself."""

    config: ExperimentConfig
    model_2d: Detector2D
    model_3d: Detector3D
    checkpoint: dict[str, Any]
    path: Path


def load_detectors(checkpoint: str | Path) -> LoadedDetectors:
    """Both detectors of a checkpoint file or a run directory (its latest checkpoint)."""
    path = resolve_checkpoint(Path(checkpoint))
    state = load_checkpoint(path)
    config = config_from_dict(state["config"])
    model_2d, model_3d = build_detectors(config)
    model_2d.load_state_dict(state["model_2d"])
    model_3d.load_state_dict(state["model_3d"])
    return LoadedDetectors(config, model_2d.eval(), model_3d.eval(), state, path)
