"""The embedded label store (docs/design.md §7): KITTI-layout files plus a SQLite index per shard.

Layout, schema, migration and crash recovery: `serving.store_layout`; listing, checking and
exporting every shard: `serving.store_export`. Each server replica writes its own shard, and
a shard is written by one process at a time (an exclusive lock).

Keys are (namespace, frame id): a namespace is a data set (`kitti-training`, `site-a`;
`default` when a request names none), so the same frame id in two data sets never collides.

Re-labeling policy: the store keeps one labeling per key, the latest. A `put` of a stored key
- is UNCHANGED when everything it would store is byte-identical to what is stored (the same
  model version and thresholds on the same frame: a retry); nothing is written;
- REPLACES the stored frame and labels otherwise (another model version, other thresholds, or
  other sensor data under the key), and says which model version it replaced.
A new key is CREATED.

Durability and group commit: an acknowledged `put` survives SIGKILL and power loss. Each
caller writes its frame's files to temporary files beside their final names, in its own
thread. One committer thread takes every frame that is waiting and, for all of them
together: fsyncs every temporary file and every directory holding them in one concurrent
round (the file system folds concurrent fsyncs into a few journal commits), commits one
SQLite transaction (WAL, synchronous=FULL) whose rows list each file's SHA-256, renames the
temporary files to their final names, and acknowledges. The row is the commit point: a kill
before it leaves temporary files no row wants (deleted by the next open); a kill after it
leaves, at worst, durable temporary files holding exactly what a row lists (renamed into
place by the next open, and read there by `serving.store_export` meanwhile). A replaced
frame therefore shows either all its old files or all its new ones.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import queue
import secrets
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from detmatch.data.kitti import format_objects, validate_frame_id, write_calib
from detmatch.files import fsync_path
from detmatch.structures import Calibration
from serving.errors import StoreError
from serving.labeler import FrameLabels
from serving.serialize import label_records, labels_to_json, labels_to_objects_3d
from serving.store_export import check_integrity, export_store, list_frames
from serving.store_index import Index, SharedStore, SqliteIndex, store_files_root
from serving.store_layout import (
    LEGACY_NAMESPACE,
    LOCK_FILE,
    SHARDS_DIR,
    StoredFrame,
    frame_paths,
    recover,
    sha256,
)

__all__ = [
    "DEFAULT_NAMESPACE",
    "LabelStore",
    "PutResult",
    "StoreOutcome",
    "StoredFrame",
    "check_integrity",
    "export_store",
    "list_frames",
    "validate_namespace",
]

log = logging.getLogger("detmatch.serving")

DEFAULT_NAMESPACE = LEGACY_NAMESPACE
IO_THREADS = 16


def validate_namespace(namespace: str) -> str:
    """Namespaces are directory names: the frame id's rules (1-64 letters, digits, '_', '-'),
    and no leading '-' (a directory named -rf is a trap for shell tools)."""
    try:
        validate_frame_id(namespace)
    except ValueError:
        raise ValueError(
            f"invalid namespace {namespace!r}: use 1-64 letters, digits, '_' or '-'"
        ) from None
    if namespace.startswith("-"):
        raise ValueError(f"invalid namespace {namespace!r}: it starts with '-'")
    return namespace


class StoreOutcome(str, Enum):
    """What a put did to the store (see the module docstring's policy)."""

    CREATED = "created"
    UNCHANGED = "unchanged"
    REPLACED = "replaced"


@dataclass(frozen=True)
class PutResult:
    """The key's record after the put; previous_version: the model version whose labels were
    stored before (None when CREATED)."""

    record: StoredFrame
    outcome: StoreOutcome
    previous_version: str | None = None


@dataclass
class _Pending:
    record: StoredFrame
    temporaries: dict[str, Path]  # relative path -> its temporary file
    future: Future = field(default_factory=Future)


@dataclass
class CommitStats:
    """Counters of the committer (benchmarks read them)."""

    batches: int = 0
    frames: int = 0


class LabelStore:
    """One shard of a label store, opened for writing by this process; thread-safe."""

    def __init__(self, root: str | os.PathLike | SharedStore, shard: str = "default") -> None:
        """root: the store's directory, or a SharedStore (a PostgreSQL index and the root
        directory every replica mounts)."""
        self.location = root if isinstance(root, SharedStore) else Path(root)
        self.root = store_files_root(self.location)
        try:
            self.shard = validate_frame_id(shard)
        except ValueError:
            raise ValueError(f"invalid shard {shard!r}: use letters, digits, '_' or '-'") from None
        self.path = self.root / SHARDS_DIR / self.shard
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise StoreError(
                f"cannot write the label store's files at {self.path}: {error}"
            ) from None
        self._lock_file = _lock_shard(self.path)
        self._index: Index | None = None
        try:
            self._index = _open_index(self.location, self.path)
            records = self._index.shard_records(self.shard)
            recovery = recover(self.path, records)
        except BaseException:
            if self._index is not None:
                self._index.close()
            self._lock_file.close()
            raise
        # fsyncs run concurrently: the file system commits concurrent fsyncs in one journal
        # transaction (ext4, xfs), so a batch's files and directories cost about one.
        self._io = ThreadPoolExecutor(IO_THREADS, thread_name_prefix=f"store-io-{self.shard}")
        self._queue: queue.SimpleQueue[_Pending | None] = queue.SimpleQueue()
        self.stats = CommitStats()
        self._committer = threading.Thread(
            target=self._commit_loop, name=f"store-{self.shard}", daemon=True
        )
        self._committer.start()
        self._closed = False
        log.info(
            "label store opened",
            extra={"fields": {"store": str(self.root), "shard": self.shard,
                              "frames": len(records), "temporary_removed":
                              recovery.temporary_removed, "rolled_forward":
                              recovery.rolled_forward, "orphans_removed":
                              recovery.orphans_removed}},
        )  # fmt: skip

    def close(self) -> None:
        """Commit what is queued, stop the committer, release the shard."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._committer.join()
        self._io.shutdown(wait=True)
        self._index.close()
        self._lock_file.close()
        log.info(
            "label store closed",
            extra={"fields": {"shard": self.shard, "frames_committed": self.stats.frames,
                              "commits": self.stats.batches}},
        )  # fmt: skip

    def get(self, frame_id: str, namespace: str = DEFAULT_NAMESPACE) -> StoredFrame | None:
        return self._index.get((validate_namespace(namespace), validate_frame_id(frame_id)))

    def put(
        self,
        frame_id: str,
        image_png: bytes,
        points: np.ndarray | bytes,
        calib: Calibration,
        result: FrameLabels,
        namespace: str = DEFAULT_NAMESPACE,
    ) -> PutResult:
        """Store a frame and its labels under (namespace, frame_id) and wait until that is
        durable; the outcome follows the re-labeling policy. image_png: the image as PNG;
        points: (N, 4) float32, or their little-endian float32 bytes."""
        namespace, frame_id = validate_namespace(namespace), validate_frame_id(frame_id)
        if self._closed:
            raise StoreError("the label store is closed")
        contents = _contents(namespace, frame_id, image_png, points, calib, result)
        token = secrets.token_hex(6)
        calib_path = frame_paths(namespace, frame_id)["calib"]
        temporaries: dict[str, Path] = {}
        try:
            temporaries[calib_path] = self._temporary(calib_path, token)
            write_calib(temporaries[calib_path], calib)
            digests = {r: sha256(d) for r, d in contents.items()}
            digests[calib_path] = sha256(temporaries[calib_path].read_bytes())
            stored = self.get(frame_id, namespace)
            if stored is not None and stored.files == digests:  # a retry: nothing to write
                _remove(temporaries)
                return PutResult(stored, StoreOutcome.UNCHANGED, stored.model_version)
            for relative, data in contents.items():
                temporaries[relative] = self._temporary(relative, token)
                with open(temporaries[relative], "wb") as handle:
                    handle.write(data)  # fsynced by the committer, with the whole batch
        except OSError as error:
            _remove(temporaries)
            raise StoreError(f"cannot store frame {namespace}/{frame_id}: {error}") from error
        except BaseException:
            _remove(temporaries)
            raise
        matched = int(result.labels.matched.sum())
        now = time.time()
        record = StoredFrame(
            namespace=namespace,
            frame_id=frame_id,
            shard=self.shard,
            model_version=result.model_version,
            stored_at=now,
            first_stored_at=now,
            num_labels=len(result),
            num_matched=matched,
            num_lidar_only=len(result) - matched,
            provenance=[r.provenance_name for r in label_records(result)],
            files=dict(sorted(digests.items())),
        )
        pending = _Pending(record, temporaries)
        self._queue.put(pending)
        return pending.future.result()

    def _temporary(self, relative: str, token: str) -> Path:
        """A temporary file's path beside the file it will become."""
        target = self.path / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        return target.with_name(f".{target.name}.{token}.tmp")

    # --- the committer: one batch of frames at a time --------------------------------------------

    def _commit_loop(self) -> None:
        while True:
            first = self._queue.get()
            batch = [first]
            while True:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            stop = None in batch
            batch = [p for p in batch if p is not None]
            if batch:
                self._commit(batch)
            if stop:
                while True:  # puts that raced close() are refused, never left waiting
                    try:
                        late = self._queue.get_nowait()
                    except queue.Empty:
                        return
                    if late is not None:
                        late.future.set_exception(StoreError("the label store is closed"))

    def _commit(self, batch: list[_Pending]) -> None:
        try:
            results = self._commit_batch(batch)
        except (OSError, StoreError) as error:
            for pending in batch:
                _remove(pending.temporaries)
                pending.future.set_exception(
                    StoreError(f"cannot store frame {pending.record.frame_id}: {error}")
                )
            return
        except Exception as error:  # noqa: BLE001 - a bug fails its batch, not the committer
            log.exception("label store commit failed", extra={"fields": {"shard": self.shard}})
            for pending in batch:
                _remove(pending.temporaries)
                pending.future.set_exception(error)
            return
        self.stats.batches += 1
        self.stats.frames += len(batch)
        for pending, result in zip(batch, results, strict=True):
            pending.future.set_result(result)

    def _commit_batch(self, batch: list[_Pending]) -> list[PutResult]:
        # Every file is durable before any row lists it: one concurrent round of fsyncs.
        files = [t for p in batch for t in p.temporaries.values()]
        list(self._io.map(fsync_path, [*files, *{t.parent for t in files}]))
        results, written = [], []
        try:
            with self._index.locked(p.record.key for p in batch) as rows:
                for pending in batch:  # in order: a later labeling of a key lands last
                    record, before = pending.record, rows.current[pending.record.key]
                    if before is not None and before.files == record.files:
                        results.append(
                            PutResult(before, StoreOutcome.UNCHANGED, before.model_version)
                        )
                        continue
                    if before is not None:
                        record = replace(record, first_stored_at=before.first_stored_at)
                    outcome = StoreOutcome.CREATED if before is None else StoreOutcome.REPLACED
                    results.append(PutResult(record, outcome, before and before.model_version))
                    rows.current[record.key] = record
                    rows.writes.append(record)
                    written.append(pending)
        except BaseException:
            for pending in batch:
                _remove(pending.temporaries)
            raise
        chosen = {id(p) for p in written}
        for pending in batch:
            if id(pending) in chosen:
                for relative, temporary in pending.temporaries.items():
                    os.replace(temporary, self.path / relative)
            else:
                _remove(pending.temporaries)
        return results

    def __enter__(self) -> LabelStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _contents(
    namespace: str,
    frame_id: str,
    image_png: bytes,
    points: np.ndarray | bytes,
    calib: Calibration,
    result: FrameLabels,
) -> dict[str, bytes]:
    """relative path -> bytes of every file of a frame but the calibration (whose bytes
    `write_calib` makes, into its temporary file)."""
    paths = frame_paths(namespace, frame_id)
    return {
        paths["image"]: image_png,
        paths["points"]: points if isinstance(points, bytes) else _points_bytes(points),
        paths["label_2"]: format_objects(labels_to_objects_3d(result, calib), decimals=4).encode(),
        paths["labels"]: json.dumps(labels_to_json(frame_id, result)).encode(),
    }


def _points_bytes(points: np.ndarray) -> bytes:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must be (N, 4), got {points.shape}")
    return points.astype("<f4").tobytes()


def _remove(temporaries: dict[str, Path]) -> None:
    for temporary in temporaries.values():
        temporary.unlink(missing_ok=True)


def _open_index(location: Path | SharedStore, shard_dir: Path) -> Index:
    if isinstance(location, SharedStore):
        from serving.store_postgres import PostgresIndex

        return PostgresIndex(location)
    return SqliteIndex(shard_dir)


def _lock_shard(shard_dir: Path):
    """An exclusive lock on the shard for this process's lifetime (released when it exits,
    however it exits); StoreError naming the holder when another process has it."""
    handle = open(shard_dir / LOCK_FILE, "a+")  # noqa: SIM115 - held until close()
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "unknown"
        handle.close()
        raise StoreError(
            f"shard {shard_dir.name} of {shard_dir.parent.parent} is open in another process "
            f"(pid {holder}); give each server replica its own --shard"
        ) from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle
