"""The manifest of a model version, typed: what export writes, and serving and retraining read.

    ROOT/<version>/manifest.json

A frozen dataclass tree with a schema version (`format`). `Manifest.load` reads and validates
a version directory's manifest (errors name the file and the field, e.g.
`manifest.json: models.detector3d.preprocessing.grid.pillar_size needs 2 values, got 3`);
`Manifest.save` writes it atomically. Torch-free: the server reads it.

Format 2 (written since retraining rounds) adds `training.checkpoint_file`, the training
checkpoint kept inside the version directory, and `retraining`, the record of the round that
made the version (its parent version, both models' gate figures, the decision and the data
used). Format 1 manifests are still read: they have neither (the checkpoint is only referenced
by path and SHA-256).
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from detmatch.files import write_json
from detmatch.matching_policy import MatchingPolicy
from detmatch.models.pillars import PillarGrid
from detmatch.records import RecordError, from_plain, to_plain

MANIFEST_FORMAT = 2
# Formats this reader accepts: 1 (before retraining rounds), 2, and 3 (2 with a quantization
# record: an INT8 version, export.quantize).
READABLE_FORMATS = (1, 2, 3)
MANIFEST_FILE = "manifest.json"
VERSION_PATTERN = re.compile(r"^[0-9]{6,}$")


class ManifestError(ValueError):
    """A manifest that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output: dims are sizes or the names of dynamic dimensions."""

    name: str
    dtype: str
    shape: tuple[int | str, ...]


@dataclass(frozen=True)
class FileRecord:
    sha256: str
    bytes: int

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[0-9a-f]{64}", self.sha256):
            raise ValueError(f"sha256 is not a hex SHA-256 digest: {self.sha256!r}")
        if self.bytes < 0:
            raise ValueError(f"bytes must be >= 0, got {self.bytes}")


@dataclass(frozen=True)
class ImagePreprocessing:
    """How the 2D graph's input is made (inside the graph): resize to input_size (W, H) and
    normalise with mean / std per RGB channel of [0, 1] images."""

    in_graph: bool
    input: str
    steps: tuple[str, ...]
    input_size: tuple[int, int]
    mean: tuple[float, float, float]
    std: tuple[float, float, float]


@dataclass(frozen=True)
class PillarGridSpec:
    """The arguments of `detmatch.models.pillars.PillarGrid` (metres, LiDAR frame)."""

    point_cloud_range: tuple[float, float, float, float, float, float]
    pillar_size: tuple[float, float]
    max_points_per_pillar: int
    max_pillars: int

    def __post_init__(self) -> None:
        self.grid()  # PillarGrid checks the values

    def grid(self) -> PillarGrid:
        return PillarGrid(
            self.point_cloud_range,
            self.pillar_size,
            self.max_points_per_pillar,
            self.max_pillars,
        )

    @staticmethod
    def of(grid: PillarGrid) -> PillarGridSpec:
        return PillarGridSpec(
            tuple(float(v) for v in grid.point_cloud_range),
            tuple(float(v) for v in grid.pillar_size),
            int(grid.max_points_per_pillar),
            int(grid.max_pillars),
        )


@dataclass(frozen=True)
class PillarPreprocessing:
    """How the 3D graph's input is made (outside the graph): `function(points, grid)`."""

    in_graph: bool
    input: str
    function: str
    grid: PillarGridSpec


@dataclass(frozen=True)
class Postprocessing:
    in_graph: str
    boxes: str
    outside_graph: str


def _check_detector(file: str, max_detections: int, score_threshold: float) -> None:
    if Path(file).name != file or not file:
        raise ValueError(f"file must be a plain file name, got {file!r}")
    if max_detections < 1:
        raise ValueError(f"max_detections must be >= 1, got {max_detections}")
    if not 0.0 <= score_threshold < 1.0:
        raise ValueError(f"score_threshold must be in [0, 1), got {score_threshold}")


@dataclass(frozen=True)
class Model2DSpec:
    file: str
    opset: int
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    preprocessing: ImagePreprocessing
    postprocessing: Postprocessing
    max_detections: int
    score_threshold: float

    def __post_init__(self) -> None:
        _check_detector(self.file, self.max_detections, self.score_threshold)


@dataclass(frozen=True)
class Model3DSpec:
    file: str
    opset: int
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    preprocessing: PillarPreprocessing
    postprocessing: Postprocessing
    max_detections: int
    score_threshold: float

    def __post_init__(self) -> None:
        _check_detector(self.file, self.max_detections, self.score_threshold)


@dataclass(frozen=True)
class Models:
    detector2d: Model2DSpec
    detector3d: Model3DSpec


# What applies the matching policy; the manifest names it.
MATCHING_FUNCTION = "detmatch.pseudo_labels.match_detections"


@dataclass(frozen=True)
class MatchingSpec:
    """The matching policy (`detmatch.matching_policy.MatchingPolicy`) as the manifest stores
    it, in the keys every format has had: tau_hung; tau_3d_outside_view (null: no fallback);
    tau_3d_unmatched (null, or absent from older manifests: only matched objects in view);
    function: what applies it. The policy checks the values."""

    tau_hung: float
    tau_3d_outside_view: float | None
    function: str
    tau_3d_unmatched: float | None = None

    def __post_init__(self) -> None:
        _ = self.policy  # MatchingPolicy checks the values

    @property
    def policy(self) -> MatchingPolicy:
        return MatchingPolicy(self.tau_hung, self.tau_3d_outside_view, self.tau_3d_unmatched)

    @staticmethod
    def of(policy: MatchingPolicy) -> MatchingSpec:
        return MatchingSpec(
            tau_hung=policy.tau_hung,
            tau_3d_outside_view=policy.tau_3d_outside_view,
            function=MATCHING_FUNCTION,
            tau_3d_unmatched=policy.tau_3d_unmatched,
        )


@dataclass(frozen=True)
class TrainingRecord:
    """Where the models came from: the checkpoint (path and SHA-256), its step, the config it
    was trained with (data included) and its evaluation metrics. checkpoint_file (format 2): the
    checkpoint's copy inside the version directory, a plain file name whose SHA-256 is
    checkpoint_sha256; None when the version keeps only the reference `checkpoint`."""

    checkpoint: str
    checkpoint_sha256: str
    step: int
    data: dict[str, Any]
    config: dict[str, Any]
    metrics: dict[str, Any] = field(default_factory=dict)
    checkpoint_file: str | None = None

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[0-9a-f]{64}", self.checkpoint_sha256):
            raise ValueError(
                f"checkpoint_sha256 is not a hex SHA-256 digest: {self.checkpoint_sha256!r}"
            )
        name = self.checkpoint_file
        if name is not None and (not name or Path(name).name != name):
            raise ValueError(f"checkpoint_file must be a plain file name, got {name!r}")


GATED_MODALITIES = ("2d", "3d")


@dataclass(frozen=True)
class GateFigures:
    """One model's moderate R40 AP (percent) on a gate split: per class and "mAP", for 2D
    boxes, 3D boxes and bird's-eye-view boxes."""

    ap_2d: dict[str, float]
    ap_3d: dict[str, float]
    ap_bev: dict[str, float]

    def __post_init__(self) -> None:
        for name in ("ap_2d", "ap_3d", "ap_bev"):
            values = getattr(self, name)
            if "mAP" not in values:
                raise ValueError(f"{name} has no mAP")
            for key, value in values.items():
                if not (math.isfinite(value) and 0.0 <= value <= 100.0):
                    raise ValueError(f"{name}.{key} must be an AP in [0, 100], got {value}")

    def map(self, modality: str) -> float:
        """The headline mAP of a modality: "2d", "3d" or "bev"."""
        return getattr(self, f"ap_{modality}")["mAP"]


def gate_passes(candidate: GateFigures, parent: GateFigures, max_map_drop: float) -> bool:
    """The promotion rule of a retraining round: in neither modality (2D, 3D) does the
    candidate's moderate mAP fall more than max_map_drop points below the parent's."""
    return all(
        candidate.map(modality) >= parent.map(modality) - max_map_drop
        for modality in GATED_MODALITIES
    )


@dataclass(frozen=True)
class RoundData:
    """The frames a retraining round trained on, by source, and the gate's. store_snapshot:
    `retrain.snapshot`'s id of the label store's content that was read; stored_labels: how
    stored frames were used ("pool": unlabeled, "labeled": their labels as fixed targets);
    excluded: stored frames left out because they are gate frames (identical point clouds)."""

    labeled: int
    unlabeled: int
    stored: int
    gate: int
    excluded: int
    store_snapshot: str
    stored_labels: str
    data_root: str
    splits: dict[str, str]
    reviewed: int = 0  # human-reviewed stored frames among `stored`, used as labeled frames
    reviewed_gate: int = 0  # of those, held out in the gate

    def __post_init__(self) -> None:
        for name in ("labeled", "unlabeled", "stored", "gate", "excluded"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not re.fullmatch(r"[0-9a-f]{64}", self.store_snapshot):
            raise ValueError(f"store_snapshot is not a hex SHA-256 digest: {self.store_snapshot!r}")


@dataclass(frozen=True)
class RetrainingRecord:
    """The retraining round that made a version: it trained `steps` steps from parent_version,
    scored both models on the same gate split, and `passed` says whether the candidate met
    `gate_passes` with max_map_drop (the PROMOTED marker says whether it was promoted).
    config: the config the round was asked for, naming the original data set's splits (the
    next round starts from it; training.config is what the round's own run used)."""

    round_id: str
    parent_version: str
    started_at: str
    method: str
    steps: int
    max_map_drop: float
    candidate: GateFigures
    parent: GateFigures
    passed: bool
    data: RoundData
    config: dict[str, Any]

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[A-Za-z0-9_\-]{1,64}", self.round_id):
            raise ValueError(f"round_id: invalid round id {self.round_id!r}")
        if not VERSION_PATTERN.match(self.parent_version):
            raise ValueError(
                f"parent_version: expected six or more digits, got {self.parent_version!r}"
            )
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if not (math.isfinite(self.max_map_drop) and self.max_map_drop >= 0):
            raise ValueError(f"max_map_drop must be >= 0, got {self.max_map_drop}")
        if self.passed != gate_passes(self.candidate, self.parent, self.max_map_drop):
            raise ValueError(
                f"passed: {self.passed} contradicts the figures (2D mAP {self.candidate.map('2d')}"
                f" vs {self.parent.map('2d')}, 3D mAP {self.candidate.map('3d')} vs "
                f"{self.parent.map('3d')}, max drop {self.max_map_drop})"
            )


@dataclass(frozen=True)
class QuantizationRecord:
    """How an INT8 version was made from an fp32 one (export.quantize): the scheme, the
    source version, the calibration frames, and label parity on held-out frames (the share of
    the source's matched labels reproduced, and the minimum it had to reach)."""

    scheme: str
    source_version: str
    calibration_data: str
    calibration_frames: int
    parity_frames: int
    matched_labels: int
    reproduced: int
    agreement: float
    min_agreement: float

    def __post_init__(self) -> None:
        if not VERSION_PATTERN.match(self.source_version):
            raise ValueError(f"source_version: expected six or more digits, got "
                             f"{self.source_version!r}")  # fmt: skip
        if not 0 <= self.reproduced <= self.matched_labels:
            raise ValueError(f"reproduced: {self.reproduced} of {self.matched_labels}")
        if self.agreement < self.min_agreement:
            raise ValueError(
                f"agreement {self.agreement} is below min_agreement {self.min_agreement}: "
                "such a version is never published"
            )


@dataclass(frozen=True)
class Manifest:
    format: int
    version: str
    exported_at: str
    classes: tuple[str, ...]
    models: Models
    matching: MatchingSpec
    training: TrainingRecord
    parity: dict[str, Any]
    tools: dict[str, str]
    files: dict[str, FileRecord]
    retraining: RetrainingRecord | None = None
    quantization: QuantizationRecord | None = None

    def __post_init__(self) -> None:
        if self.format not in READABLE_FORMATS:
            raise ValueError(
                f"format: manifest format {self.format!r}, this reader knows "
                f"{', '.join(map(str, READABLE_FORMATS))}"
            )
        if self.format < 2 and (self.retraining or self.training.checkpoint_file):
            raise ValueError(
                "format: a format 1 manifest has no retraining record and no checkpoint_file"
            )
        if (self.format == 3) != (self.quantization is not None):
            raise ValueError("format: format 3, and only format 3, has a quantization record")
        if self.quantization is not None and self.quantization.source_version == self.version:
            raise ValueError(f"quantization.source_version: {self.version} is this version")
        if self.retraining is not None and self.retraining.parent_version == self.version:
            raise ValueError(f"retraining.parent_version: {self.version} is this version")
        if not VERSION_PATTERN.match(self.version):
            raise ValueError(f"version: expected six or more digits, got {self.version!r}")
        if not self.classes or len(set(self.classes)) != len(self.classes):
            raise ValueError(f"classes: expected distinct class names, got {self.classes}")
        for name in self.files:
            if Path(name).name != name or not name:
                raise ValueError(f"files: file name {name!r} is not plain")
        if self.training.checkpoint_file in self.files:
            raise ValueError("training.checkpoint_file: the checkpoint is not a serving file")
        for key in ("detector2d", "detector3d"):
            listed = getattr(self.models, key).file
            if listed not in self.files:
                raise ValueError(f"models.{key}.file: {listed!r} has no checksum under files")

    @property
    def model_2d(self) -> Model2DSpec:
        return self.models.detector2d

    @property
    def model_3d(self) -> Model3DSpec:
        return self.models.detector3d

    def to_json(self) -> dict[str, Any]:
        return to_plain(self)

    @staticmethod
    def from_json(data: Any, where: str = MANIFEST_FILE) -> Manifest:
        """Validate plain JSON data; ManifestError names `where` and the field."""
        if isinstance(data, dict) and data.get("format") not in READABLE_FORMATS:
            raise ManifestError(
                f"{where}: manifest format {data.get('format')!r}, this reader knows "
                f"{', '.join(map(str, READABLE_FORMATS))}"
            )
        try:
            return from_plain(Manifest, data, "")
        except RecordError as error:
            raise ManifestError(f"{where}: {error}") from None

    @staticmethod
    def load(directory: str | os.PathLike) -> Manifest:
        """The manifest of a version directory."""
        path = Path(directory) / MANIFEST_FILE
        if not path.is_file():
            raise ManifestError(f"{directory} has no {MANIFEST_FILE}")
        try:
            data = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise ManifestError(f"{path}: not valid JSON: {error}") from None
        return Manifest.from_json(data, str(path))

    def save(self, directory: str | os.PathLike) -> Path:
        """Write DIRECTORY/manifest.json atomically and durably; returns its path."""
        path = Path(directory) / MANIFEST_FILE
        write_json(path, self.to_json())
        return path
