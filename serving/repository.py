"""The versioned model repository: what `detmatch-export` writes and the labeler reads.

    ROOT/000001/manifest.json        classes, inputs, preprocessing, thresholds, checksums, ...
    ROOT/000001/detector2d.onnx
    ROOT/000001/detector3d.onnx
    ROOT/000001/checkpoint.pt        the training checkpoint (retraining continues from it)
    ROOT/000001/PROMOTED             present when the version may serve (a marker file)
    ROOT/.staging-XXXX/              an export in progress: never a version

Versions are positive integers written with at least six digits and ordered by their number
("000010" comes after "000009"); an export without an explicit version takes the highest
existing number plus one. A version directory appears in one `rename` of a fully written,
fsynced staging directory, so a reader sees a complete version or none; versions are never
modified afterwards, except for the PROMOTED marker. The served version is the newest version
carrying the marker; removing the marker from a bad version rolls back to the previous one.

No torch: the server and the exporter share it. Files are written with `detmatch.files`'
atomic writer (temporary file, fsync, rename, directory fsync).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from detmatch.files import atomic_write_bytes, fsync_path, sha256_file
from serving.manifest import VERSION_PATTERN, FileRecord, Manifest, ManifestError

PROMOTED_FILE = "PROMOTED"
MODEL_2D_FILE = "detector2d.onnx"
MODEL_3D_FILE = "detector3d.onnx"
CHECKPOINT_FILE = "checkpoint.pt"
STAGING_PREFIX = ".staging-"
# A staging directory this old belongs to an export that was killed.
STALE_STAGING_SECONDS = 24 * 3600

# Graph input and output names: the contract between the exporter and the labeler (the graphs
# also output each detector's raw head maps, named by its `output_names`).
INPUTS_2D = ("image",)
INPUTS_3D = ("features", "coords", "num_points")
DECODED_OUTPUTS = ("boxes", "scores", "classes", "probabilities")
# Every input and output of both graphs leads with this dynamic axis: a call labels a batch.
BATCH_AXIS = "batch"


class RepositoryError(ValueError):
    """A repository, version or manifest that cannot be used; the message says why."""


def format_version(number: int) -> str:
    if not isinstance(number, int) or isinstance(number, bool) or number < 1:
        raise RepositoryError(f"a version is a positive integer, got {number!r}")
    return f"{number:06d}"


def parse_version(version: str | int) -> str:
    """'7', 7 or '000007' -> '000007'."""
    if isinstance(version, int):
        return format_version(version)
    text = str(version).strip()
    if not text.isdigit() or not text.isascii():
        raise RepositoryError(f"a version is a positive integer, got {version!r}")
    return format_version(int(text))


def list_versions(root: str | os.PathLike) -> list[str]:
    """Published versions of a repository, oldest (lowest number) first."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"no model repository at {root}")
    found = [p.name for p in root.iterdir() if VERSION_PATTERN.match(p.name) and p.is_dir()]
    return sorted(found, key=int)


def version_dir(root: str | os.PathLike, version: str | int) -> Path:
    """The directory of a published version; FileNotFoundError when there is none."""
    path = Path(root) / parse_version(version)
    if not path.is_dir():
        raise FileNotFoundError(f"model repository {root} has no version {parse_version(version)}")
    return path


def promoted_versions(root: str | os.PathLike) -> list[str]:
    """Versions carrying the PROMOTED marker, oldest first."""
    return [v for v in list_versions(root) if (Path(root) / v / PROMOTED_FILE).is_file()]


def served_version(root: str | os.PathLike) -> str | None:
    """The version a server should serve: the newest promoted one (None if none is)."""
    promoted = promoted_versions(root)
    return promoted[-1] if promoted else None


def promote(root: str | os.PathLike, version: str | int) -> str:
    """Mark a published version as allowed to serve; returns its name. Idempotent. A version
    that fails `verify_version` is refused (RepositoryError saying why)."""
    path = version_dir(root, version)
    try:
        verify_version(path)
    except RepositoryError as error:
        raise RepositoryError(f"refusing to promote {path.name}: {error}") from None
    record = {"promoted_at": _utc_now()}
    atomic_write_bytes(path / PROMOTED_FILE, (json.dumps(record) + "\n").encode(), durable=True)
    return path.name


def demote(root: str | os.PathLike, version: str | int) -> str:
    """Remove a version's PROMOTED marker (a rollback to the previous promoted version)."""
    path = version_dir(root, version)
    (path / PROMOTED_FILE).unlink(missing_ok=True)
    fsync_path(path)
    return path.name


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Read and validate the manifest of a version directory (RepositoryError naming the field
    when it cannot be used)."""
    try:
        return Manifest.load(path)
    except ManifestError as error:
        raise RepositoryError(str(error)) from None


def file_record(path: str | os.PathLike) -> FileRecord:
    """A file's SHA-256 and size, as the manifest lists it."""
    return FileRecord(sha256=sha256_file(path), bytes=Path(path).stat().st_size)


def verify_checksums(path: str | os.PathLike, manifest: Manifest | None = None) -> None:
    """Check every file the manifest lists against its size and SHA-256."""
    path = Path(path)
    manifest = load_manifest(path) if manifest is None else manifest
    for name, expected in manifest.files.items():
        file = path / name
        if not file.is_file():
            raise RepositoryError(f"{file} is listed in the manifest but missing")
        if file.stat().st_size != expected.bytes or sha256_file(file) != expected.sha256:
            raise RepositoryError(f"{file} does not match its checksum in the manifest")


def verify_version(path: str | os.PathLike, manifest: Manifest | None = None) -> Manifest:
    """What a version must pass to be promoted or served: a valid manifest that names the
    version's own directory (a hand-copied folder keeps the version it was copied from) and
    files that match their checksums. Returns the manifest."""
    path = Path(path)
    manifest = load_manifest(path) if manifest is None else manifest
    if manifest.version != path.name:
        raise RepositoryError(
            f"{path / 'manifest.json'} names version {manifest.version}, not {path.name}: a "
            "version directory must be published by detmatch-export, not copied by hand"
        )
    verify_checksums(path, manifest)
    return manifest


def training_checkpoint(path: str | os.PathLike, manifest: Manifest | None = None) -> Path:
    """The training checkpoint a version's models came from, checked against the manifest's
    SHA-256: the copy inside the version directory (training.checkpoint_file), else the file
    the manifest references (format 1, or an export without the copy). RepositoryError when it
    is missing or does not match."""
    path = Path(path)
    manifest = load_manifest(path) if manifest is None else manifest
    training = manifest.training
    if training.checkpoint_file is not None:
        checkpoint = path / training.checkpoint_file
        where = f"{checkpoint} (the version's copy)"
    else:
        checkpoint = Path(training.checkpoint)
        where = f"{checkpoint} (referenced by {path / 'manifest.json'}; not kept in the version)"
    if not checkpoint.is_file():
        raise RepositoryError(f"version {path.name}'s training checkpoint is missing: {where}")
    if sha256_file(checkpoint) != training.checkpoint_sha256:
        raise RepositoryError(
            f"version {path.name}'s training checkpoint {where} does not match the SHA-256 in "
            "its manifest"
        )
    return checkpoint


@contextlib.contextmanager
def staging_directory(root: str | os.PathLike) -> Iterator[Path]:
    """A fresh hidden directory inside the repository for one export; removed on exit unless
    it was published (renamed) in the meantime. Stale staging directories of killed exports
    (older than a day) are removed on the way in."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(root)
    staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=root))
    os.chmod(staging, 0o755)  # readable by a server running as another user once published
    try:
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def remove_stale_staging(root: Path, older_than_s: float = STALE_STAGING_SECONDS) -> None:
    now = time.time()
    for path in Path(root).glob(f"{STAGING_PREFIX}*"):
        with contextlib.suppress(OSError):
            if now - path.stat().st_mtime > older_than_s:
                shutil.rmtree(path, ignore_errors=True)


def next_version(root: str | os.PathLike) -> str:
    existing = list_versions(root)
    return format_version(int(existing[-1]) + 1 if existing else 1)


def publish(
    root: str | os.PathLike,
    staging: Path,
    version: str | int | None = None,
    finalize: Callable[[str], None] | None = None,
) -> tuple[str, Path]:
    """Move a staging directory to ROOT/<version> in one rename.

    finalize(version) runs first and writes what depends on the version's name (the
    manifest); then every file and the directory are fsynced and renamed. With version None
    the next number is taken, retrying if a concurrent export takes it first; an explicit
    version that exists already is an error: published versions are immutable. Returns
    (version, its directory).
    """
    root = Path(root)
    for _ in range(100):
        name = next_version(root) if version is None else parse_version(version)
        target = root / name
        if target.exists():
            if version is None:
                continue
            raise RepositoryError(
                f"version {name} already exists in {root}; versions are immutable"
            )
        if finalize is not None:
            finalize(name)
        for file in staging.iterdir():
            with open(file, "rb") as handle:
                os.fsync(handle.fileno())
        fsync_path(staging)
        try:
            os.rename(staging, target)
        except OSError:
            # A concurrent export published the same number between the check and the rename.
            if version is None and target.exists():
                continue
            raise
        fsync_path(root)
        return name, target
    raise RepositoryError(f"could not find a free version number in {root}")


def _utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
