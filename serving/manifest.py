"""The manifest of a model version, typed: what export writes, and serving and retraining read.

    ROOT/<version>/manifest.json

A frozen dataclass tree with a schema version (`format`). `Manifest.load` reads and validates
a version directory's manifest (errors name the file and the field, e.g.
`manifest.json: models.detector3d.preprocessing.grid.pillar_size needs 2 values, got 3`);
`Manifest.save` writes it atomically. Torch-free: the server reads it.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from detmatch.files import write_json
from detmatch.models.pillars import PillarGrid
from detmatch.records import RecordError, from_plain, to_plain

MANIFEST_FORMAT = 1
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


@dataclass(frozen=True)
class MatchingSpec:
    """tau_hung: the matching threshold; tau_3d_outside_view: the score above which 3D boxes
    outside the camera's view become LiDAR-only labels (None: no fallback)."""

    tau_hung: float
    tau_3d_outside_view: float | None
    function: str

    def __post_init__(self) -> None:
        outside = self.tau_3d_outside_view
        if outside is not None and not 0.0 <= outside < 1.0:
            raise ValueError(f"tau_3d_outside_view must be in [0, 1) or null, got {outside}")


@dataclass(frozen=True)
class TrainingRecord:
    """Where the models came from: the checkpoint (path and SHA-256), its step, the config it
    was trained with (data included) and its evaluation metrics."""

    checkpoint: str
    checkpoint_sha256: str
    step: int
    data: dict[str, Any]
    config: dict[str, Any]
    metrics: dict[str, Any] = field(default_factory=dict)


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

    def __post_init__(self) -> None:
        if self.format != MANIFEST_FORMAT:
            raise ValueError(
                f"format: manifest format {self.format!r}, this reader knows {MANIFEST_FORMAT}"
            )
        if not VERSION_PATTERN.match(self.version):
            raise ValueError(f"version: expected six or more digits, got {self.version!r}")
        if not self.classes or len(set(self.classes)) != len(self.classes):
            raise ValueError(f"classes: expected distinct class names, got {self.classes}")
        for name in self.files:
            if Path(name).name != name or not name:
                raise ValueError(f"files: file name {name!r} is not plain")
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
        if isinstance(data, dict) and data.get("format") != MANIFEST_FORMAT:
            raise ManifestError(
                f"{where}: manifest format {data.get('format')!r}, this reader knows "
                f"{MANIFEST_FORMAT}"
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
