"""Where the label store keeps a frame, its index schema, and what opening a shard repairs.

    STORE/shards/<shard>/index.sqlite           schema 2, WAL journal: one row per key
                                                (namespace, frame id)
    STORE/shards/<shard>/.lock                  held (flock) by the process writing the shard
    STORE/shards/<shard>/namespaces/<namespace>/training/image_2/ID.png
                                               .../training/velodyne/ID.bin
                                               .../training/calib/ID.txt
                                               .../training/label_2/ID.txt  KITTI result rows
                                               .../labels/ID.json           every label

Each namespace directory is a KITTI-layout data set of its own. Schema 1 (before namespaces:
one row per bare frame id, files at `shards/<shard>/training/...`) is migrated when a shard is
opened for writing: its files move under namespace `default` and its rows gain the
namespace, in a way a kill can interrupt and the next open finishes. Readers
(`serving.store_export`) read both schemas without migrating.

Opening a shard for writing also recovers from a killed writer: a temporary file whose
content is what a committed row lists for its target is renamed into place (a replacement
interrupted after its commit), every other temporary file is deleted, and so is every frame
file no committed row lists (a frame killed before its commit).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import sqlite3
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from detmatch.data.kitti import FRAME_ID_PATTERN
from detmatch.files import fsync_path

log = logging.getLogger("detmatch.serving")

SHARDS_DIR = "shards"
NAMESPACES_DIR = "namespaces"
INDEX_FILE = "index.sqlite"
LOCK_FILE = ".lock"
SCHEMA_VERSION = 2
LEGACY_NAMESPACE = "default"  # where schema 1's frames go
# kind -> (directory relative to a namespace, file suffix)
FRAME_FILES = {
    "image": ("training/image_2", ".png"),
    "points": ("training/velodyne", ".bin"),
    "calib": ("training/calib", ".txt"),
    "label_2": ("training/label_2", ".txt"),
    "labels": ("labels", ".json"),
}
COLUMNS = (
    "namespace", "frame_id", "model_version", "stored_at", "first_stored_at", "num_labels",
    "num_matched", "num_lidar_only", "provenance", "files",
)  # fmt: skip
SCHEMA = """
CREATE TABLE IF NOT EXISTS frames (
    namespace TEXT NOT NULL,
    frame_id TEXT NOT NULL,
    model_version TEXT NOT NULL,
    stored_at REAL NOT NULL,
    first_stored_at REAL NOT NULL,
    num_labels INTEGER NOT NULL,
    num_matched INTEGER NOT NULL,
    num_lidar_only INTEGER NOT NULL,
    provenance TEXT NOT NULL,
    files TEXT NOT NULL,
    PRIMARY KEY (namespace, frame_id)
)
"""
# A temporary file: `.<target name>.<random>.tmp` beside its target.
TEMPORARY = re.compile(r"^\.(?P<target>.+)\.[^.]+\.tmp$")


@dataclass(frozen=True)
class StoredFrame:
    """One index row. files: path relative to the shard -> SHA-256 of every file of the frame;
    stored_at: when these labels were stored; first_stored_at: when the key first was."""

    namespace: str
    frame_id: str
    shard: str
    model_version: str
    stored_at: float
    first_stored_at: float
    num_labels: int
    num_matched: int
    num_lidar_only: int
    provenance: list[str]
    files: dict[str, str]

    @property
    def key(self) -> tuple[str, str]:
        return self.namespace, self.frame_id

    def row(self) -> tuple:
        return (
            self.namespace, self.frame_id, self.model_version, self.stored_at,
            self.first_stored_at, self.num_labels, self.num_matched, self.num_lidar_only,
            json.dumps(self.provenance), json.dumps(self.files, sort_keys=True),
        )  # fmt: skip


def frame_paths(namespace: str, frame_id: str) -> dict[str, str]:
    """kind -> path relative to the shard of each file of a frame."""
    return {
        kind: f"{NAMESPACES_DIR}/{namespace}/{directory}/{frame_id}{suffix}"
        for kind, (directory, suffix) in FRAME_FILES.items()
    }


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def record_of(row: sqlite3.Row | tuple, shard: str) -> StoredFrame:
    """A schema 2 row -> StoredFrame."""
    values = dict(zip(COLUMNS, row, strict=True))
    return StoredFrame(
        namespace=values["namespace"],
        frame_id=values["frame_id"],
        shard=shard,
        model_version=values["model_version"],
        stored_at=float(values["stored_at"]),
        first_stored_at=float(values["first_stored_at"]),
        num_labels=int(values["num_labels"]),
        num_matched=int(values["num_matched"]),
        num_lidar_only=int(values["num_lidar_only"]),
        provenance=json.loads(values["provenance"]),
        files=json.loads(values["files"]),
    )


def schema_version(db: sqlite3.Connection) -> int:
    """2 for this schema, 1 for the index before namespaces, 0 for an empty database."""
    version = db.execute("PRAGMA user_version").fetchone()[0]
    if version:
        return int(version)
    columns = [r[1] for r in db.execute("PRAGMA table_info(frames)")]
    return 1 if columns else 0


def read_records(index: Path) -> list[StoredFrame]:
    """Every row of a shard's index, read-only, either schema (schema 1 rows are read as
    namespace LEGACY_NAMESPACE with their files where schema 1 put them)."""
    db = sqlite3.connect(f"file:{index}?mode=ro", uri=True)
    try:
        version = schema_version(db)
        if version == 1:
            return [_legacy_record(r, index.parent.name) for r in db.execute(LEGACY_SELECT)]
        if version == 0:
            return []
        if version != SCHEMA_VERSION:
            raise ValueError(f"{index}: label store schema {version}, this reader knows <= 2")
        rows = db.execute(f"SELECT {', '.join(COLUMNS)} FROM frames").fetchall()
    finally:
        db.close()
    return [record_of(r, index.parent.name) for r in rows]


LEGACY_SELECT = (
    "SELECT frame_id, model_version, stored_at, num_labels, num_matched, num_lidar_only, "
    "provenance, files FROM frames"
)


def _legacy_record(row: tuple, shard: str, moved: bool = False) -> StoredFrame:
    frame_id, version, stored_at, labels, matched, lidar_only, provenance, files = row
    files = json.loads(files)
    if moved:
        files = {f"{NAMESPACES_DIR}/{LEGACY_NAMESPACE}/{k}": v for k, v in files.items()}
    return StoredFrame(
        LEGACY_NAMESPACE, frame_id, shard, version, float(stored_at), float(stored_at),
        int(labels), int(matched), int(lidar_only), json.loads(provenance), files,
    )  # fmt: skip


@contextmanager
def transaction(db: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """One explicit transaction (the connection is in autocommit mode, so DDL is inside it
    too): committed on success, rolled back on any error."""
    db.execute("BEGIN IMMEDIATE")
    try:
        yield db
    except BaseException:
        db.execute("ROLLBACK")
        raise
    db.execute("COMMIT")


def open_index(shard_dir: Path) -> sqlite3.Connection:
    """The shard's index at schema 2 (created, or migrated from schema 1). The connection is
    in autocommit mode: writes go through `transaction`."""
    db = sqlite3.connect(
        str(shard_dir / INDEX_FILE), check_same_thread=False, timeout=30.0, isolation_level=None
    )
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=FULL")
    version = schema_version(db)
    if version == 1:
        _migrate_schema_1(db, shard_dir)
    elif version == 0:
        with transaction(db):
            db.execute(SCHEMA)
            db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
    elif version != SCHEMA_VERSION:
        db.close()
        raise ValueError(f"{shard_dir}: label store schema {version}, this server knows <= 2")
    return db


def _migrate_schema_1(db: sqlite3.Connection, shard_dir: Path) -> None:
    """Move schema 1's files under namespace LEGACY_NAMESPACE, then rewrite the index in one
    transaction. Moving is idempotent (a file already moved is skipped), so a migration
    killed half way is finished by the next open."""
    records = [_legacy_record(r, shard_dir.name, moved=True) for r in db.execute(LEGACY_SELECT)]
    directories = set()
    for record in records:
        for relative in record.files:
            target = shard_dir / relative
            source = shard_dir / relative.split("/", 2)[2]
            if source.is_file():
                target.parent.mkdir(parents=True, exist_ok=True)
                os.replace(source, target)
                directories |= {source.parent, target.parent}
    for directory in directories:
        fsync_path(directory)
    with transaction(db):
        db.execute("ALTER TABLE frames RENAME TO frames_schema_1")
        db.execute(SCHEMA)
        db.executemany(
            f"INSERT INTO frames VALUES ({', '.join('?' * len(COLUMNS))})",
            [r.row() for r in records],
        )
        db.execute("DROP TABLE frames_schema_1")
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
    log.info(
        "label store migrated",
        extra={"fields": {"shard": str(shard_dir), "from_schema": 1, "to_schema": SCHEMA_VERSION,
                          "frames": len(records), "namespace": LEGACY_NAMESPACE}},
    )  # fmt: skip


@dataclass(frozen=True)
class Recovery:
    temporary_removed: int = 0
    rolled_forward: int = 0
    orphans_removed: int = 0


def recover(shard_dir: Path, records: Iterable[StoredFrame]) -> Recovery:
    """Repair a shard after a killed writer (see the module docstring). Only files that look
    like the store's own (a frame file of a valid id, or a temporary file) are touched."""
    listed = {relative: digest for record in records for relative, digest in record.files.items()}
    temporary = rolled = orphans = 0
    touched = set()
    for directory in _frame_directories(shard_dir):
        for path in sorted(directory.iterdir()):
            if not path.is_file():
                continue
            relative = path.relative_to(shard_dir).as_posix()
            match = TEMPORARY.match(path.name)
            if match:
                target = path.with_name(match["target"])
                wanted = listed.get(target.relative_to(shard_dir).as_posix())
                if wanted is not None and _digest(path) == wanted and _digest(target) != wanted:
                    os.replace(path, target)
                    rolled += 1
                else:
                    path.unlink()
                    temporary += 1
                touched.add(directory)
            elif relative not in listed and _is_frame_file(path):
                path.unlink()
                orphans += 1
                touched.add(directory)
    for directory in touched:
        fsync_path(directory)
    for legacy in (shard_dir / "training", shard_dir / "labels"):
        _remove_empty_directories(legacy)
    return Recovery(temporary, rolled, orphans)


def resolve_file(shard_dir: Path, relative: str, digest: str) -> Path | None:
    """Where a row's file holds its content: its final path, or, for a frame committed but
    not yet renamed into place (in flight, or killed in between), a temporary file beside it
    whose SHA-256 is the row's; None when neither does."""
    path = shard_dir / relative
    if _digest(path) == digest:
        return path
    for candidate in sorted(path.parent.glob(f".{path.name}.*.tmp")):
        if _digest(candidate) == digest:
            return candidate
    return None


def _frame_directories(shard_dir: Path) -> list[Path]:
    roots = [shard_dir]  # schema 1's directories: only debris is left there after migration
    namespaces = shard_dir / NAMESPACES_DIR
    if namespaces.is_dir():
        roots += sorted(p for p in namespaces.iterdir() if p.is_dir())
    return [
        root / directory
        for root in roots
        for directory, _ in FRAME_FILES.values()
        if (root / directory).is_dir()
    ]


def _is_frame_file(path: Path) -> bool:
    suffixes = {suffix for _, suffix in FRAME_FILES.values()}
    return path.suffix in suffixes and bool(FRAME_ID_PATTERN.match(path.stem))


def _digest(path: Path) -> str | None:
    try:
        return sha256(path.read_bytes())
    except FileNotFoundError:
        return None


def _remove_empty_directories(root: Path) -> None:
    if not root.is_dir():
        return
    for directory in sorted((p for p in root.rglob("*") if p.is_dir()), reverse=True):
        if not any(directory.iterdir()):
            directory.rmdir()
    if not any(root.iterdir()):
        root.rmdir()
