"""A checkpoint -> a checked, published model version.

export_checkpoint(checkpoint, repository)
  1. load both detectors (eval mode) from the checkpoint or run directory;
  2. in a hidden staging directory of the repository: export both graphs (export.graphs),
     onnx.checker (full check) on each;
  3. onnxruntime, with the serving session options, against PyTorch on synthetic and
     real frames (export.parity); any disagreement raises ParityError;
  4. a copy of the training checkpoint (unless keep_checkpoint is False: then the manifest
     only references it by path and SHA-256), manifest.json with the files' checksums (and
     the retraining round's record, for a version a round made); rename the staging
     directory to the version;
  5. optionally promote the version.
Any failure removes the staging directory: no version appears.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from detmatch.models.build import load_detectors
from detmatch.models.pillars import pillarize
from export.graphs import export_detector_2d, export_detector_3d
from export.manifest import build_manifest
from export.parity import ParityError, ParityReport, Tolerance, check_parity, load_parity_frames
from serving.manifest import RetrainingRecord
from serving.repository import (
    CHECKPOINT_FILE,
    MODEL_2D_FILE,
    MODEL_3D_FILE,
    RepositoryError,
    parse_version,
    promote,
    publish,
    staging_directory,
)
from serving.sessions import SessionSettings, make_session


@dataclass(frozen=True)
class ExportResult:
    version: str
    path: Path
    promoted: bool
    parity: ParityReport


def export_checkpoint(
    checkpoint: str | os.PathLike,
    repository: str | os.PathLike,
    version: str | int | None = None,
    promote_version: bool = False,
    parity_data: Sequence[str | os.PathLike] | None = None,
    parity_frames_per_source: int = 3,
    synthetic_frames: int = 2,
    tolerance: Tolerance | None = None,
    log: Callable[[str], None] | None = None,
    keep_checkpoint: bool = True,
    retraining: RetrainingRecord | None = None,
) -> ExportResult:
    """Export, check and publish a checkpoint (see the module docstring).

    Parity runs on `synthetic_frames` rendered frames and on up to `parity_frames_per_source`
    frames of each KITTI-layout directory of parity_data; None means the checkpoint's own
    training data ([data] root) when it is there. keep_checkpoint: copy the checkpoint into
    the version (what `detmatch retrain` continues from). retraining: the record of the round
    that made these models. Raises ExportCheckError (ParityError) when a check fails,
    RepositoryError when the version exists.
    """
    log = log or (lambda message: None)
    tolerance = tolerance or Tolerance()
    repository = Path(repository)
    if version is not None:
        version = parse_version(version)
        if (repository / version).exists():
            raise RepositoryError(f"version {version} already exists in {repository}")
    loaded = load_detectors(checkpoint)
    config, model_2d, model_3d = loaded.config, loaded.model_2d, loaded.model_3d
    checkpoint_file, state = loaded.path, loaded.checkpoint
    log(f"loaded {checkpoint_file} (step {state.get('step')})")
    if parity_data is None:
        training_data = Path(config.data.root)
        parity_data = [training_data] if (training_data / "training" / "image_2").is_dir() else []
        found = ", ".join(str(path) for path in parity_data) or "not found"
        log(f"parity frames from the training data: {found}")
    if synthetic_frames < 1 and not parity_data:
        raise ValueError("parity needs frames: synthetic_frames >= 1 or some parity_data")
    frames = load_parity_frames(synthetic_frames, parity_data, parity_frames_per_source)
    started = time.time()

    with staging_directory(repository) as staging:
        _, example = frames[0]
        export_detector_2d(model_2d, config.data.image_size, staging / MODEL_2D_FILE, example.image)
        export_detector_3d(
            model_3d,
            staging / MODEL_3D_FILE,
            pillarize(example.points, model_3d.grid).arrays,
        )
        log("exported both graphs; onnx.checker passed")
        settings = SessionSettings()
        report = check_parity(
            make_session(staging / MODEL_2D_FILE, settings),
            make_session(staging / MODEL_3D_FILE, settings),
            model_2d,
            model_3d,
            config,
            frames,
            tolerance,
        )
        if not report.passed:
            raise ParityError(f"onnxruntime disagrees with PyTorch: {report.summary()}")
        log(f"parity: {report.summary()}")

        kept = None
        if keep_checkpoint:
            shutil.copyfile(checkpoint_file, staging / CHECKPOINT_FILE)
            kept = CHECKPOINT_FILE

        def write_manifest(name: str) -> None:
            manifest = build_manifest(
                name, staging, config, state, checkpoint_file, report, started, model_3d.grid,
                checkpoint_copy=kept, retraining=retraining,
            )  # fmt: skip
            manifest.save(staging)

        name, path = publish(repository, staging, version, finalize=write_manifest)
    log(f"published version {name} at {path}")
    if promote_version:
        promote(repository, name)
        log(f"promoted version {name}")
    return ExportResult(name, path, promote_version, report)
