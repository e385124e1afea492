"""Experiment configuration: frozen dataclasses loaded from TOML; unknown keys are errors.

A config file has one table per section below ([data], [detector2d], [detector3d], [train],
[ssl]);
every key is optional and defaults to the values here. Loss weights and learning rates are
named fields, never string lookups.
"""

from __future__ import annotations

import dataclasses
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from detmatch.constants import SCORE_THRESHOLD, TAU_2D, TAU_3D, TAU_HUNG
from detmatch.records import RecordError, coerce, to_plain

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


class ConfigError(ValueError):
    """A config file with an unknown key, a wrong type or an invalid value."""


BOXES_2D_SOURCES = ("annotated", "projected")

# Where training runs: "auto" (the first CUDA GPU when torch sees one, else the CPU), "cpu"
# or "cuda".
DEVICES = ("auto", "cpu", "cuda")
# The forward passes' precision (detmatch.training.precision).
PRECISIONS = ("auto", "fp32", "bf16")


@dataclass(frozen=True)
class DataConfig:
    """Where the frames are and which classes the detectors learn."""

    root: str = "data/synth"
    train_split: str = "train"
    val_split: str = "val"
    classes: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
    # Images are resized to this (W, H) before the 2D detector; boxes are mapped back.
    image_size: tuple[int, int] = (624, 192)
    num_workers: int = 0
    # The 2D detector's training boxes: "annotated" (the label files' 2D boxes) or
    # "projected" (each 3D label's box projected into the image, as the authors' code trains
    # it: the same convention as the projected 3D boxes the consistency loss compares with).
    # Evaluation always uses the annotated boxes.
    train_boxes_2d: str = "annotated"

    def __post_init__(self) -> None:
        if self.train_boxes_2d not in BOXES_2D_SOURCES:
            raise ConfigError(
                f"[data] train_boxes_2d must be one of {', '.join(BOXES_2D_SOURCES)}, "
                f"got {self.train_boxes_2d!r}"
            )


@dataclass(frozen=True)
class Detector2DConfig:
    """The camera detector. type: a name of `detmatch.models.build.DETECTORS_2D` ("centernet":
    a CenterNet-style strided conv backbone with stride-4 heads, which the other keys shape)."""

    type: str = "centernet"
    widths: tuple[int, ...] = (16, 32, 64, 128)
    depths: tuple[int, ...] = (1, 1, 2, 2)
    head_width: int = 64
    max_detections: int = 50
    score_threshold: float = SCORE_THRESHOLD
    heatmap_weight: float = 1.0
    size_weight: float = 0.1
    offset_weight: float = 1.0


@dataclass(frozen=True)
class Detector3DConfig:
    """The LiDAR detector. type: a name of `detmatch.models.build.DETECTORS_3D`
    ("pointpillars": a PointPillars encoder + CenterPoint-style head, which the other keys
    shape). Ranges in metres, LiDAR frame."""

    type: str = "pointpillars"
    point_cloud_range: tuple[float, ...] = (0.0, -32.0, -3.0, 64.0, 32.0, 1.0)
    pillar_size: tuple[float, float] = (0.25, 0.25)
    max_points_per_pillar: int = 20
    max_pillars: int = 16000
    pillar_channels: int = 32
    widths: tuple[int, ...] = (32, 64, 128)
    depths: tuple[int, ...] = (2, 3, 3)
    head_width: int = 64
    # The head's output stride relative to the pillar grid.
    out_stride: int = 2
    max_detections: int = 50
    score_threshold: float = SCORE_THRESHOLD
    heatmap_weight: float = 1.0
    regression_weight: float = 0.25


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation (DESIGN.md section 3): SGD for 2D, AdamW for 3D, warm-up then constant."""

    steps: int = 2000
    batch_size: int = 4
    lr_2d: float = 0.01
    lr_3d: float = 0.002
    momentum_2d: float = 0.9
    weight_decay_2d: float = 1e-4
    betas_3d: tuple[float, float] = (0.95, 0.99)
    weight_decay_3d: float = 0.01
    warmup_steps: int = 100
    grad_clip: float = 10.0
    eval_every: int = 500
    checkpoint_every: int = 250
    log_every: int = 10
    seed: int = 0
    flip_probability: float = 0.5
    # "auto" (bf16 autocast where the CPU or GPU computes bf16 natively), "fp32" or "bf16":
    # the forward passes' precision; losses, decoding, matching and the EMA stay fp32.
    precision: str = "auto"

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ConfigError(
                f"[train] precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}"
            )


METHODS = ("labeled-only", "confidence", "detmatch")


@dataclass(frozen=True)
class SemiSupervisedConfig:
    """Teacher-student training (DESIGN.md section 3). method: labeled-only, confidence
    (single-modality thresholding) or detmatch. The labeled frames are [data] train_split."""

    method: str = "labeled-only"
    unlabeled_split: str = "train_unlabeled"
    # Checkpoint (or run directory) of the labeled-only pre-training both students start from.
    pretrained: str = ""
    tau_3d: float = TAU_3D
    tau_2d: float = TAU_2D
    tau_hung: float = TAU_HUNG
    # lambda: weight of both pseudo-label losses.
    pseudo_label_weight: float = 1.0
    # DetMatch weights the 2D pseudo-label (classification) loss x4 relative to the 3D one.
    detmatch_2d_pseudo_weight: float = 4.0
    # 3D boxes outside the camera's view fall back to confidence thresholding (tau_3d).
    fov_fallback: bool = True
    # Ablation switches of the 2D-teacher -> 3D-student consistency loss.
    consistency_class: bool = True
    consistency_box: bool = True
    consistency_class_weight: float = 2.0
    consistency_l1_weight: float = 20.0
    consistency_giou_weight: float = 2.0
    ema_offset: int = 100
    ema_max_decay: float = 0.999
    student_rotation: float = 0.7853981633974483
    student_scale: tuple[float, float] = (0.95, 1.05)
    photometric: bool = True

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(
                f"[ssl] method must be one of {', '.join(METHODS)}, got {self.method!r}"
            )


@dataclass(frozen=True)
class ExperimentConfig:
    data: DataConfig = field(default_factory=DataConfig)
    detector2d: Detector2DConfig = field(default_factory=Detector2DConfig)
    detector3d: Detector3DConfig = field(default_factory=Detector3DConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    ssl: SemiSupervisedConfig = field(default_factory=SemiSupervisedConfig)

    def replace(self, section: str, **changes: Any) -> ExperimentConfig:
        """A copy with some fields of one section changed (validated like a file)."""
        current = dataclasses.asdict(getattr(self, section))
        unknown = set(changes) - set(current)
        if unknown:
            raise ConfigError(f"[{section}] has no key {sorted(unknown)[0]!r}")
        current.update(changes)
        section_type = type(getattr(self, section))
        return dataclasses.replace(self, **{section: _build(section_type, current, section)})


def _build(section_type: type, values: dict[str, Any], section: str) -> Any:
    hints = typing.get_type_hints(section_type)
    known = {f.name for f in dataclasses.fields(section_type)}
    for key in values:
        if key not in known:
            raise ConfigError(
                f"unknown key {key!r} in [{section}]; known keys: {', '.join(sorted(known))}"
            )
    try:
        kwargs = {k: coerce(v, hints[k], f"[{section}] {k}") for k, v in values.items()}
    except RecordError as error:
        raise ConfigError(str(error)) from None
    return section_type(**kwargs)


def config_from_dict(raw: dict[str, Any]) -> ExperimentConfig:
    sections = {f.name: f.type for f in dataclasses.fields(ExperimentConfig)}
    hints = typing.get_type_hints(ExperimentConfig)
    built = {}
    for name, values in raw.items():
        if name not in sections:
            raise ConfigError(f"unknown section [{name}]; known sections: {', '.join(sections)}")
        if not isinstance(values, dict):
            raise ConfigError(f"[{name}] must be a table")
        built[name] = _build(hints[name], values, name)
    return ExperimentConfig(**built)


def load_config(path: str | Path) -> ExperimentConfig:
    """Read a TOML config; unknown sections or keys raise ConfigError naming them."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: {error}") from None
    try:
        return config_from_dict(raw)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None


def config_to_dict(config: ExperimentConfig) -> dict[str, Any]:
    """Plain nested dict (tuples as lists): for checkpoints and manifests."""
    return {
        section: to_plain(getattr(config, section))
        for section in ("data", "detector2d", "detector3d", "train", "ssl")
    }
