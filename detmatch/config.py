"""Experiment configuration: frozen dataclasses loaded from TOML; unknown keys are errors.

A config file has one table per section below ([data], [detector2d], [detector3d], [train],
[ssl], [retrain]); every key is optional and defaults to the values here. Loss weights and
learning rates are named fields, never string lookups. Every section checks its values' ranges
when it is built (`__post_init__`), so a file, a `--set section.key=value` override and code
all get the same ConfigError naming the section and the key.

`load_config` takes a path or the name of a config shipped inside the package
(`detmatch.configs`, the repository's configs/ directory): `load_config("tiny")`.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
import sys
import typing
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from detmatch.constants import (
    CONSISTENCY_CLASS_WEIGHT,
    CONSISTENCY_GIOU_WEIGHT,
    CONSISTENCY_L1_WEIGHT,
    SCORE_THRESHOLD,
    TAU_2D,
    TAU_3D,
    TAU_HUNG,
)
from detmatch.records import RecordError, coerce, to_plain

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


class ConfigError(ValueError):
    """A config file with an unknown key, a wrong type or an invalid value."""


class _Checks:
    """Range checks of one section's values; a failure is a ConfigError naming [section] key.
    Tuple values are checked element by element. Floats must also be finite."""

    def __init__(self, record: Any) -> None:
        self.record = record
        self.section = record.SECTION

    def fail(self, key: str, expected: str) -> None:
        value = getattr(self.record, key)
        raise ConfigError(f"[{self.section}] {key} must be {expected}, got {_show(value)}")

    def _each(self, keys: Iterable[str], ok, expected: str) -> None:
        for key in keys:
            value = getattr(self.record, key)
            values = value if isinstance(value, tuple) else (value,)
            if not all(_finite(v) and ok(v) for v in values):
                self.fail(key, expected)

    def positive(self, *keys: str) -> None:
        self._each(keys, lambda v: v > 0, "> 0")

    def non_negative(self, *keys: str) -> None:
        self._each(keys, lambda v: v >= 0, ">= 0")

    def probability(self, *keys: str) -> None:
        self._each(keys, lambda v: 0 <= v <= 1, "in [0, 1]")

    def below_one(self, *keys: str) -> None:
        self._each(keys, lambda v: 0 <= v < 1, "in [0, 1)")

    def finite(self, *keys: str) -> None:
        self._each(keys, lambda v: True, "a finite number")

    def one_of(self, key: str, choices: Sequence[str]) -> None:
        if getattr(self.record, key) not in choices:
            self.fail(key, f"one of {', '.join(choices)}")

    def name(self, *keys: str) -> None:
        """Names used in file names and KITTI rows: non-empty, no whitespace or '/'."""
        for key in keys:
            value = getattr(self.record, key)
            values = value if isinstance(value, tuple) else (value,)
            if not all(v and not any(c.isspace() or c == "/" for c in v) for v in values):
                self.fail(key, "non-empty names without whitespace or '/'")


def _finite(value: Any) -> bool:
    return not isinstance(value, float) or math.isfinite(value)


def _show(value: Any) -> str:
    return repr(list(value)) if isinstance(value, tuple) else repr(value)


BOXES_2D_SOURCES = ("annotated", "projected")

# Where training runs: "auto" (the first CUDA GPU when torch sees one, else the CPU), "cpu"
# or "cuda".
DEVICES = ("auto", "cpu", "cuda")
# The forward passes' precision (detmatch.precision).
PRECISIONS = ("auto", "fp32", "bf16")
SCHEDULES_2D = ("constant", "step")
SCHEDULES_3D = ("constant", "onecycle")


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
    train_boxes_2d: str = "projected"

    SECTION: ClassVar[str] = "data"

    def __post_init__(self) -> None:
        check = _Checks(self)
        check.one_of("train_boxes_2d", BOXES_2D_SOURCES)
        if not self.root:
            check.fail("root", "a directory")
        check.name("train_split", "val_split", "classes")
        if not self.classes:
            check.fail("classes", "a list of at least one class")
        if len(set(self.classes)) != len(self.classes):
            check.fail("classes", "distinct names")
        check.positive("image_size")
        check.non_negative("num_workers")


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

    SECTION: ClassVar[str] = "detector2d"

    def __post_init__(self) -> None:
        check = _Checks(self)
        check.name("type")
        check.positive("widths", "head_width", "max_detections")
        check.non_negative("depths", "heatmap_weight", "size_weight", "offset_weight")
        if not self.widths:
            check.fail("widths", "at least one stage width")
        if len(self.depths) != len(self.widths):
            check.fail("depths", f"a list of one entry per stage ({len(self.widths)}, as widths)")
        check.probability("score_threshold")

    @property
    def stride(self) -> int:
        """The backbone's total stride (each stage halves the image): input sizes divide by it."""
        return 2 ** len(self.widths)


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
    # A light second stage (detmatch.models.refine): detached boxes refined from detached BEV
    # features; the consistency loss then trains it instead of the dense box regression.
    refine: bool = False
    refine_weight: float = 1.0

    SECTION: ClassVar[str] = "detector3d"

    def __post_init__(self) -> None:
        check = _Checks(self)
        check.name("type")
        check.finite("point_cloud_range")
        check.positive("pillar_size", "max_points_per_pillar", "max_pillars", "pillar_channels")
        check.positive("widths", "head_width", "out_stride", "max_detections")
        check.non_negative("depths", "heatmap_weight", "regression_weight", "refine_weight")
        if not self.widths:
            check.fail("widths", "at least one stage width")
        if len(self.depths) != len(self.widths):
            check.fail("depths", f"a list of one entry per stage ({len(self.widths)}, as widths)")
        check.probability("score_threshold")
        bounds = self.point_cloud_range
        if len(bounds) != 6 or not all(bounds[i + 3] > bounds[i] for i in range(3)):
            check.fail("point_cloud_range", "[x_min, y_min, z_min, x_max, y_max, z_max], max > min")
        for axis in (0, 1):  # the pillar grid covers the x and y ranges in whole cells
            extent = bounds[axis + 3] - bounds[axis]
            cells = extent / self.pillar_size[axis]
            if abs(cells - round(cells)) > 1e-6:
                check.fail("pillar_size", f"a divisor of the {'xy'[axis]} range ({extent:g} m)")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation (docs/design.md section 3): SGD for 2D, AdamW for 3D, warm-up then constant."""

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
    # Learning-rate schedules over `steps` (after the linear warm-up): "constant"; for 2D
    # "step" (x0.1 at each fraction of milestones_2d); for 3D "onecycle" (cosine from
    # lr_3d / onecycle_div up to lr_3d at the fraction onecycle_peak, then cosine down to
    # lr_3d / onecycle_div / 1e4: OpenPCDet's one-cycle, momentum not cycled).
    schedule_2d: str = "constant"
    milestones_2d: tuple[float, ...] = (0.67, 0.89)
    schedule_3d: str = "constant"
    onecycle_peak: float = 0.4
    onecycle_div: float = 10.0
    # A checkpoint (or run directory: its latest) whose 2D detector starts this run instead of
    # random weights, as the paper's camera starts from COCO; "" starts from scratch. Its
    # [detector2d] and classes must be this config's. A resumed run loads its own weights.
    init_2d: str = ""

    SECTION: ClassVar[str] = "train"

    def __post_init__(self) -> None:
        check = _Checks(self)
        check.one_of("precision", PRECISIONS)
        check.one_of("schedule_2d", SCHEDULES_2D)
        check.one_of("schedule_3d", SCHEDULES_3D)
        check.probability("milestones_2d", "onecycle_peak")
        check.positive("onecycle_div")
        check.positive("steps", "batch_size", "lr_2d", "lr_3d", "grad_clip")
        check.positive("eval_every", "checkpoint_every", "log_every")
        check.non_negative("weight_decay_2d", "weight_decay_3d", "warmup_steps", "seed")
        check.below_one("momentum_2d", "betas_3d")
        check.probability("flip_probability")


@dataclass(frozen=True)
class AugmentConfig:
    """Augmentation of labeled frames, in pre-training and in the labeled half of
    teacher-student steps (docs/design.md section 3; the flip is [train] flip_probability, shared
    by image and cloud). 3D only (the image and the 2D targets untouched unless
    gt_sampling_image): ground-truth database sampling (objects of other labeled frames pasted
    into the cloud with their points), then global rotation about z in +-rotation radians and
    global scale in scale.
    2D only: image_scale, a random rescale of the image before it is cropped or padded to
    [data] image_size (multi-scale training; [1, 1] is off). repeat_factor_threshold: frames
    holding rare classes are drawn more often (detectron2's repeat-factor sampling; 0 is off).
    """

    gt_sampling: bool = True
    # Objects of each class ([data] classes order) a frame is filled up to by sampling.
    gt_sample_counts: tuple[int, ...] = (15, 10, 10)
    gt_min_points: int = 5
    # Paste the sampled objects' image crops too (the rig is the same in every frame), so the
    # 2D detector learns them as well; objects whose 2D box would touch another are not
    # sampled then.
    gt_sampling_image: bool = False
    rotation: float = 0.7853981633974483
    scale: tuple[float, float] = (0.95, 1.05)
    image_scale: tuple[float, float] = (1.0, 1.0)
    repeat_factor_threshold: float = 0.0

    SECTION: ClassVar[str] = "augment"

    def __post_init__(self) -> None:
        check = _Checks(self)
        check.non_negative("gt_sample_counts", "gt_min_points", "rotation")
        check.positive("scale", "image_scale")
        check.probability("repeat_factor_threshold")
        for key in ("scale", "image_scale"):
            low, high = getattr(self, key)
            if low > high:
                check.fail(key, "[low, high] with low <= high")


# labeled-only: pre-training (SupervisedTrainer); labeled-only-control: a pre-trained model
# continued on labeled frames with the teacher-student run's EMA teacher and no unlabeled loss.
METHODS = ("labeled-only", "labeled-only-control", "confidence", "detmatch")


@dataclass(frozen=True)
class SemiSupervisedConfig:
    """Teacher-student training (docs/design.md section 3). method: labeled-only, confidence
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
    # DetMatch: in-view 3D teacher detections the matching leaves unmatched whose max class
    # probability exceeds this become LiDAR-only pseudo-labels (the camera misses occluded and
    # small objects the LiDAR sees). 1.0: off (the paper: only matched objects in view). 0.6
    # won on dev over three split seeds: +1.3 3D mAP, +0.1 2D mAP against the paper's rule
    # (BENCHMARKS.md, "LiDAR-only pseudo-labels with the 2D side protected"); 0.6 is where dev's
    # 3D pseudo-label F1 peaks in every class. Their image projections are ignore regions of the
    # 2D student (no background where the LiDAR is confident and the camera was silent).
    tau_3d_unmatched: float = 0.6
    # Switches of the 2D-teacher -> 3D-student consistency loss. Off by default: on dev its box
    # term, on the dense head, shortened cars and cost 2.7 3D mAP against matching only, which
    # tied it routed into [detector3d] refine (BENCHMARKS.md, issue 14); PRESETS["paper"] and
    # `--preset paper` turn both on.
    consistency_class: bool = False
    consistency_box: bool = False
    consistency_class_weight: float = CONSISTENCY_CLASS_WEIGHT
    consistency_l1_weight: float = CONSISTENCY_L1_WEIGHT
    consistency_giou_weight: float = CONSISTENCY_GIOU_WEIGHT
    # The teacher-student stage's own schedule (every method but labeled-only), which
    # `teacher_student_config` puts in [train] for the run: `steps` steps at these rates,
    # constant after a `warmup_steps` linear warm-up; [train]'s steps, rates and schedules are
    # pre-training's. Chosen on dev (BENCHMARKS.md, "The stage's length and learning rate"):
    # 1,200 steps at 0.1x the benchmark pre-training's rates (the paper keeps its pre-training
    # rates: at 1.0x DetMatch's 2D collapsed on dev). The rates default to 0.1x [train]'s
    # defaults; every shipped config sets them at 0.1x its own.
    steps: int = 1200
    lr_2d: float = 0.001
    lr_3d: float = 0.0002
    warmup_steps: int = 50
    ema_offset: int = 100
    ema_max_decay: float = 0.999
    student_rotation: float = 0.7853981633974483
    student_scale: tuple[float, float] = (0.95, 1.05)
    photometric: bool = True

    SECTION: ClassVar[str] = "ssl"

    def __post_init__(self) -> None:
        check = _Checks(self)
        check.one_of("method", METHODS)
        check.name("unlabeled_split")
        check.probability("tau_3d", "tau_2d", "tau_3d_unmatched")
        check.finite("tau_hung")
        check.non_negative("pseudo_label_weight", "detmatch_2d_pseudo_weight")
        check.non_negative(
            "consistency_class_weight", "consistency_l1_weight", "consistency_giou_weight"
        )
        check.positive("ema_offset", "steps", "lr_2d", "lr_3d")
        check.non_negative("warmup_steps")
        check.below_one("ema_max_decay")
        check.non_negative("student_rotation")
        check.positive("student_scale")
        if self.student_scale[0] > self.student_scale[1]:
            check.fail("student_scale", "[low, high] with low <= high")


# How a retraining round uses the label store's frames: "pool" (they join the unlabeled pool
# and the teachers label them afresh each step) or "labeled" (their stored labels are fixed
# training targets: the frames join the labeled frames).
STORED_LABEL_USES = ("pool", "labeled")


@dataclass(frozen=True)
class RetrainConfig:
    """A retraining round (`detmatch retrain`): teacher-student training of `steps` steps from
    the promoted version, promoted only if neither modality's moderate mAP on the gate split
    ([data] val_split) falls more than max_map_drop points (AP percent) below the promoted
    version's. stored_labels: one of STORED_LABEL_USES (default: the unlabeled pool).
    reviewed_gate_fraction: the share of human-reviewed frames (3D reviews, `detmatch review
    import`) held out in the gate split, chosen by a hash of each key (the others join the
    labeled frames)."""

    steps: int = 200
    max_map_drop: float = 1.0
    stored_labels: str = "pool"
    reviewed_gate_fraction: float = 0.0

    SECTION: ClassVar[str] = "retrain"

    def __post_init__(self) -> None:
        check = _Checks(self)
        check.positive("steps")
        check.non_negative("max_map_drop")
        check.one_of("stored_labels", STORED_LABEL_USES)
        if not 0.0 <= self.reviewed_gate_fraction < 1.0:
            check.fail("reviewed_gate_fraction", "a share in [0, 1)")


@dataclass(frozen=True)
class ExperimentConfig:
    data: DataConfig = field(default_factory=DataConfig)
    detector2d: Detector2DConfig = field(default_factory=Detector2DConfig)
    detector3d: Detector3DConfig = field(default_factory=Detector3DConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    ssl: SemiSupervisedConfig = field(default_factory=SemiSupervisedConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    retrain: RetrainConfig = field(default_factory=RetrainConfig)

    def __post_init__(self) -> None:
        if len(self.augment.gt_sample_counts) != len(self.data.classes):
            raise ConfigError(
                f"[augment] gt_sample_counts needs one count per class of [data] classes "
                f"({len(self.data.classes)}), got {list(self.augment.gt_sample_counts)}"
            )
        stride = self.detector2d.stride
        if any(size % stride for size in self.data.image_size):
            raise ConfigError(
                f"[data] image_size must be multiples of {stride}, the 2D backbone's stride "
                f"(2 ** len([detector2d] widths)), got {list(self.data.image_size)}"
            )

    def replace(self, section: str, **changes: Any) -> ExperimentConfig:
        """A copy with some fields of one section changed (validated like a file)."""
        current = dataclasses.asdict(getattr(self, section))
        current.update(changes)
        section_type = type(getattr(self, section))
        return dataclasses.replace(self, **{section: _build(section_type, current, section)})


# Keys deleted from the config once dev had decided them (issue 40), each with a test of whether
# a value is what the code still does: a saved run's config (a checkpoint, a retraining round's
# state) holding one loads as before; another value is an error naming the commit that has it.
RETIRED_AT = "651fd4f"
RETIRED_KEYS: dict[tuple[str, str], Callable[[Any, dict[str, Any]], bool]] = {
    ("ssl", "fov_fallback"): lambda value, _: value is True,
    ("ssl", "consistency_reduction"): lambda value, _: value == "pairs",
    ("ssl", "consistency_nms"): lambda value, _: value is False,
    ("ssl", "pseudo_2d_normalizer"): lambda value, _: value == "pseudo-labels",
    ("ssl", "consistency_targets"): lambda value, _: value == "teacher",
    ("ssl", "ignore_unmatched_score_3d"): lambda value, _: value == 1.0,
    ("ssl", "ignore_unmatched_score_2d"): lambda value, _: value == 1.0,
    # Off made no difference without LiDAR-only labels (the paper preset's tau_3d_unmatched 1.0).
    ("ssl", "lidar_only_ignore_2d"): lambda value, section: (
        value is True
        or section.get("tau_3d_unmatched", SemiSupervisedConfig.tau_3d_unmatched) >= 1.0
    ),
}


def _without_retired(section: str, values: dict[str, Any]) -> dict[str, Any]:
    kept = {}
    for key, value in values.items():
        still_done = RETIRED_KEYS.get((section, key))
        if still_done is None:
            kept[key] = value
        elif not still_done(value, values):
            raise ConfigError(
                f"[{section}] {key} = {value!r} is no longer an option (dev decided it; "
                f"BENCHMARKS.md): commit {RETIRED_AT} has it"
            )
    return kept


def _build(section_type: type, values: dict[str, Any], section: str) -> Any:
    values = _without_retired(section, values)
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


# The configs shipped inside the package: the repository's configs/ directory, installed as
# this package (setup.py maps it), so `--config tiny` works from a wheel as from a checkout.
PACKAGED_CONFIGS = "detmatch.configs"


def packaged_configs() -> list[str]:
    """Names of the configs shipped inside the package, for `load_config(name)`."""
    return sorted(
        entry.name.removesuffix(".toml")
        for entry in importlib.resources.files(PACKAGED_CONFIGS).iterdir()
        if entry.name.endswith(".toml")
    )


def read_config_text(name_or_path: str | Path) -> tuple[str, str]:
    """(TOML text, where it came from) of a config file, or else of the packaged config of
    that name ("tiny" or "tiny.toml"). A path that exists always wins over a packaged name."""
    path = Path(name_or_path)
    if path.is_file():
        return path.read_text(), str(path)
    name = str(name_or_path).removesuffix(".toml")
    available = packaged_configs()
    if path.name == str(name_or_path) and name in available:
        resource = importlib.resources.files(PACKAGED_CONFIGS) / f"{name}.toml"
        return resource.read_text(), f"packaged config {name!r}"
    raise FileNotFoundError(
        f"no config file {str(name_or_path)!r} and no packaged config of that name; "
        f"packaged configs: {', '.join(available)}"
    )


# The [train] keys a teacher-student run takes from its [ssl] stage (teacher_student_config):
# the [ssl] key that sets each, or None for the schedules, which are constant in the stage.
STAGE_KEYS: dict[str, str | None] = {
    "steps": "steps", "lr_2d": "lr_2d", "lr_3d": "lr_3d", "warmup_steps": "warmup_steps",
    "schedule_2d": None, "schedule_3d": None,
}  # fmt: skip


def teacher_student_config(config: ExperimentConfig) -> ExperimentConfig:
    """The config a run of config.ssl.method trains with: for a teacher-student method, [ssl]'s
    stage schedule (steps, rates, warm-up; constant rates) in place of [train]'s pre-training
    one; a labeled-only config unchanged. Applying it twice changes nothing, so a run's saved
    config can start the next run (a retraining round)."""
    if config.ssl.method == "labeled-only":
        return config
    stage = {key: getattr(config.ssl, source) if source else "constant"
             for key, source in STAGE_KEYS.items()}  # fmt: skip
    return config.replace("train", **stage)


def refuse_pretraining_overrides(config: ExperimentConfig, overrides: Sequence[str]) -> None:
    """ConfigError for a `--set train.KEY` that a teacher-student run of config would not use
    (KEY is one of STAGE_KEYS: the run trains [ssl]'s stage), naming what to set instead."""
    if config.ssl.method == "labeled-only":
        return
    for text in overrides:
        section, key, _ = parse_override(text)
        if section == "train" and key in STAGE_KEYS:
            source = STAGE_KEYS[key]
            instead = f"set ssl.{source}" if source else "its rates are constant after the warm-up"
            raise ConfigError(
                f"--set {text!r}: [train] {key} is pre-training's; a {config.ssl.method} run "
                f"trains the teacher-student stage of [ssl] ({instead})"
            )


def load_config(name_or_path: str | Path) -> ExperimentConfig:
    """Read a TOML config file, or a packaged config by name (`packaged_configs()`); unknown
    sections or keys and out-of-range values raise ConfigError naming them."""
    text, where = read_config_text(name_or_path)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{where}: {error}") from None
    try:
        return config_from_dict(raw)
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None


def parse_override(text: str) -> tuple[str, str, Any]:
    """`section.key=value` -> (section, key, value). The value is read as a TOML literal
    (`100`, `0.02`, `[320, 96]`, `true`, `"val"`); text that is not one is taken as a plain
    string, so `ssl.method=detmatch` needs no quotes."""
    target, equals, literal = text.partition("=")
    section, dot, key = target.strip().partition(".")
    if not equals or not dot or not section or not key or "." in key:
        raise ConfigError(f"--set {text!r}: expected section.key=value, e.g. train.steps=100")
    try:
        value = tomllib.loads(f"value = {literal.strip()}")["value"]
    except tomllib.TOMLDecodeError:
        value = literal.strip()
    return section, key, value


# Named DetMatch settings (`detmatch train --preset NAME`, the benchmark's method rows): override
# lists applied after the config file and --set. "paper": the paper's constants and loss as
# published (both consistency terms on the 3D detector's only box regressor, pairs averaged;
# only matched objects in view, so no LiDAR-only labels and no 2D ignore regions), what the
# defaults were before dev chose otherwise (BENCHMARKS.md, issue 14).
PRESETS: dict[str, tuple[str, ...]] = {
    "paper": (
        "ssl.method=detmatch", f"ssl.tau_hung={TAU_HUNG}", "ssl.consistency_class=true",
        "ssl.consistency_box=true", f"ssl.consistency_class_weight={CONSISTENCY_CLASS_WEIGHT}",
        f"ssl.consistency_l1_weight={CONSISTENCY_L1_WEIGHT}",
        f"ssl.consistency_giou_weight={CONSISTENCY_GIOU_WEIGHT}",
        "ssl.tau_3d_unmatched=1.0", "detector3d.refine=false",
    ),
}  # fmt: skip


def apply_preset(config: ExperimentConfig, name: str) -> ExperimentConfig:
    """The config with a named preset (PRESETS) applied."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}")
    return apply_overrides(config, PRESETS[name])


def apply_overrides(config: ExperimentConfig, overrides: Sequence[str]) -> ExperimentConfig:
    """The config with `section.key=value` overrides (`parse_override`) applied, all at once and
    then validated as a file is (so widths and depths can change together). Unknown sections
    and keys are ConfigErrors naming them; a string key keeps the text as written (`--set
    data.val_split=2024` is the split "2024")."""
    raw = config_to_dict(config)
    for text in overrides:
        section, key, value = parse_override(text)
        if section not in raw:
            raise ConfigError(
                f"--set {text!r}: unknown section [{section}]; known sections: {', '.join(raw)}"
            )
        if key not in raw[section]:
            raise ConfigError(
                f"--set {text!r}: unknown key {key!r} in [{section}]; known keys: "
                f"{', '.join(sorted(raw[section]))}"
            )
        if isinstance(raw[section][key], str) and not isinstance(value, str):
            value = text.partition("=")[2].strip()
        raw[section][key] = value
    return config_from_dict(raw)


def config_to_dict(config: ExperimentConfig) -> dict[str, Any]:
    """Plain nested dict (tuples as lists): for checkpoints and manifests."""
    return {
        section: to_plain(getattr(config, section))
        for section in ("data", "detector2d", "detector3d", "train", "ssl", "augment", "retrain")
    }
