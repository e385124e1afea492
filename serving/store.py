"""The embedded label store (DESIGN.md §7): KITTI-layout files plus a SQLite index per shard.

    STORE/shards/<shard>/index.sqlite            frame id, model version, time, counts,
                                                 provenance, file checksums (WAL journal)
    STORE/shards/<shard>/training/image_2/ID.png
    STORE/shards/<shard>/training/velodyne/ID.bin
    STORE/shards/<shard>/training/calib/ID.txt
    STORE/shards/<shard>/training/label_2/ID.txt KITTI result rows (3D labels in the camera's view)
    STORE/shards/<shard>/labels/ID.json          every label with costs and provenance

A frame exists once its index row is committed, and the row is committed only after every file
was written (temporary file, fsync, rename): a killed process leaves at most unreferenced files,
which the next write of that frame replaces. Writing a frame id that is already indexed
changes nothing and returns the stored record (retries are idempotent). Each server replica
writes its own shard; listing and export read every shard (the newest record of an id wins).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detmatch.data.kitti import format_objects, validate_frame_id, write_calib, write_image_set
from detmatch.files import atomic_write_bytes, fsync_path
from detmatch.structures import Calibration
from serving.errors import StoreError
from serving.labeler import FrameLabels
from serving.serialize import label_records, labels_to_json, labels_to_objects_3d

SHARDS_DIR = "shards"
SELECT_FRAME = "SELECT * FROM frames WHERE frame_id = ?"
INDEX_FILE = "index.sqlite"
SCHEMA = """
CREATE TABLE IF NOT EXISTS frames (
    frame_id TEXT PRIMARY KEY,
    model_version TEXT NOT NULL,
    stored_at REAL NOT NULL,
    num_labels INTEGER NOT NULL,
    num_matched INTEGER NOT NULL,
    num_lidar_only INTEGER NOT NULL,
    provenance TEXT NOT NULL,
    files TEXT NOT NULL
)
"""


@dataclass(frozen=True)
class StoredFrame:
    """One index row. files: relative path -> SHA-256 of every file of the frame."""

    frame_id: str
    shard: str
    model_version: str
    stored_at: float
    num_labels: int
    num_matched: int
    num_lidar_only: int
    provenance: list[str]
    files: dict[str, str]


class LabelStore:
    """One shard of a label store, safe for concurrent calls from one process's threads."""

    def __init__(self, root: str | os.PathLike, shard: str = "default") -> None:
        self.root = Path(root)
        try:
            self.shard = validate_frame_id(shard)
        except ValueError:
            raise ValueError(f"invalid shard {shard!r}: use letters, digits, '_' or '-'") from None
        self.path = self.root / SHARDS_DIR / self.shard
        self.path.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = _connect(self.path / INDEX_FILE)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def get(self, frame_id: str) -> StoredFrame | None:
        frame_id = validate_frame_id(frame_id)
        with self._lock:
            row = self._db.execute(SELECT_FRAME, (frame_id,)).fetchone()
        return None if row is None else _record(row, self.shard)

    def put(
        self,
        frame_id: str,
        image_png: bytes,
        points: np.ndarray,
        calib: Calibration,
        result: FrameLabels,
    ) -> tuple[StoredFrame, bool]:
        """Store a frame and its labels; (record, True) if written now, (the earlier record,
        False) if the frame id was already stored. image_png: the image as PNG bytes."""
        frame_id = validate_frame_id(frame_id)
        with self._lock:
            row = self._db.execute(SELECT_FRAME, (frame_id,)).fetchone()
            if row is not None:
                return _record(row, self.shard), False
            try:
                files = self._write_files(frame_id, image_png, points, calib, result)
                provenance = [r.provenance_name for r in label_records(result)]
                matched = int(result.labels.matched.sum())
                values = (
                    frame_id,
                    result.model_version,
                    time.time(),
                    len(result),
                    matched,
                    len(result) - matched,
                    json.dumps(provenance),
                    json.dumps(files, sort_keys=True),
                )
                with self._db:
                    self._db.execute("INSERT INTO frames VALUES (?, ?, ?, ?, ?, ?, ?, ?)", values)
            except (OSError, sqlite3.Error) as error:
                raise StoreError(f"cannot store frame {frame_id}: {error}") from error
            return _record(values, self.shard), True

    def _write_files(
        self,
        frame_id: str,
        image_png: bytes,
        points: np.ndarray,
        calib: Calibration,
        result: FrameLabels,
    ) -> dict[str, str]:
        training = self.path / "training"
        contents = {
            f"training/image_2/{frame_id}.png": image_png,
            f"training/velodyne/{frame_id}.bin": np.asarray(points).astype("<f4").tobytes(),
            f"training/label_2/{frame_id}.txt": format_objects(
                labels_to_objects_3d(result, calib), decimals=4
            ).encode(),
            f"labels/{frame_id}.json": json.dumps(labels_to_json(frame_id, result)).encode(),
        }
        calib_path = training / "calib" / f"{frame_id}.txt"
        write_calib(calib_path, calib)
        fsync_path(calib_path)
        contents[f"training/calib/{frame_id}.txt"] = calib_path.read_bytes()
        for relative, data in contents.items():
            if relative.startswith("training/calib/"):
                continue
            atomic_write_bytes(self.path / relative, data, durable=True)
        for directory in {(self.path / r).parent for r in contents}:
            fsync_path(directory)
        return {r: hashlib.sha256(d).hexdigest() for r, d in contents.items()}


def list_frames(root: str | os.PathLike) -> list[StoredFrame]:
    """Every stored frame of every shard, one record per frame id (the newest), sorted by id."""
    newest: dict[str, StoredFrame] = {}
    shards = Path(root) / SHARDS_DIR
    for index in sorted(shards.glob(f"*/{INDEX_FILE}")):
        db = sqlite3.connect(f"file:{index}?mode=ro", uri=True)
        try:
            rows = db.execute("SELECT * FROM frames").fetchall()
        finally:
            db.close()
        for row in rows:
            record = _record(row, index.parent.name)
            if (
                record.frame_id not in newest
                or record.stored_at > newest[record.frame_id].stored_at
            ):
                newest[record.frame_id] = record
    return [newest[k] for k in sorted(newest)]


def check_integrity(root: str | os.PathLike) -> list[str]:
    """Problems found: SQLite integrity checks and every indexed file's checksum (empty: fine)."""
    problems = []
    for index in sorted((Path(root) / SHARDS_DIR).glob(f"*/{INDEX_FILE}")):
        db = sqlite3.connect(str(index))
        try:
            result = db.execute("PRAGMA integrity_check").fetchone()[0]
        finally:
            db.close()
        if result != "ok":
            problems.append(f"{index}: {result}")
    for record in list_frames(root):
        base = Path(root) / SHARDS_DIR / record.shard
        for relative, digest in record.files.items():
            path = base / relative
            if not path.is_file():
                problems.append(f"{path}: missing")
            elif hashlib.sha256(path.read_bytes()).hexdigest() != digest:
                problems.append(f"{path}: checksum mismatch")
    return problems


def export_store(root: str | os.PathLike, out: str | os.PathLike) -> int:
    """A KITTI-layout data set of every stored frame (label_2 holds its labels) plus
    ImageSets/train.txt and labels/ID.json; returns the number of frames."""
    root, out = Path(root), Path(out)
    records = list_frames(root)
    for record in records:
        base = root / SHARDS_DIR / record.shard
        for relative in record.files:
            target = out / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(base / relative, target)
    write_image_set(out / "ImageSets" / "train.txt", [r.frame_id for r in records])
    return len(records)


def _connect(path: Path) -> sqlite3.Connection:
    db = sqlite3.connect(str(path), check_same_thread=False, timeout=30.0)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=FULL")
    db.execute(SCHEMA)
    db.commit()
    return db


def _record(row: tuple, shard: str) -> StoredFrame:
    return StoredFrame(
        frame_id=row[0],
        shard=shard,
        model_version=row[1],
        stored_at=float(row[2]),
        num_labels=int(row[3]),
        num_matched=int(row[4]),
        num_lidar_only=int(row[5]),
        provenance=json.loads(row[6]),
        files=json.loads(row[7]),
    )
