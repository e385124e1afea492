"""Reading a label store whole: every shard, either schema, without taking any shard's lock
(servers may be writing). `list_frames`, `check_integrity`, and `export_store` (`detmatch
store export`), which writes a KITTI-layout data set that `detmatch train` runs on directly.

Which record of a key wins when several shards hold it: the latest `stored_at`, then the
higher model version, then the shard name; so a listing or an export of the same store is
always the same, and it follows the re-labeling policy (the latest labeling wins).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from detmatch.data.kitti import FRAME_ID_PATTERN, write_image_set
from detmatch.files import atomic_write_bytes
from serving.store_index import SharedStore, store_files_root
from serving.store_layout import (
    FRAME_FILES,
    INDEX_FILE,
    NAMESPACES_DIR,
    SHARDS_DIR,
    StoredFrame,
    read_records,
    resolve_file,
)

Store = str | os.PathLike | SharedStore  # a store's directory, or a shared store
DEFAULT_VAL_FRACTION = 0.1
EXPORT_MANIFEST = "export.json"
NAMESPACE_SEPARATOR = "__"
# A file whose checksum does not match its row may be a replacement in flight on a live
# server: read the row again this many times before giving up.
READ_RETRIES = 5


def _precedence(record: StoredFrame) -> tuple:
    version = int(record.model_version) if record.model_version.isdigit() else -1
    return record.stored_at, version, record.shard


def _shard_indexes(root: str | os.PathLike) -> list[Path]:
    return sorted((Path(root) / SHARDS_DIR).glob(f"*/{INDEX_FILE}"))


def _all_records(store: Store) -> Iterable[StoredFrame]:
    """Every index row: of every shard's SQLite index, or of a shared store's PostgreSQL one."""
    if isinstance(store, SharedStore):
        from serving.store_postgres import read_all

        yield from read_all(store)
        return
    for index in _shard_indexes(store):
        yield from read_records(index)


def list_frames(store: Store, namespace: str | None = None) -> list[StoredFrame]:
    """One record per key (the winning one, see the module docstring) of every shard, sorted
    by (namespace, frame id); only `namespace`'s when given. store: the store's directory or
    a SharedStore (whose index holds one row per key already)."""
    winners: dict[tuple[str, str], StoredFrame] = {}
    for record in _all_records(store):
        if namespace is not None and record.namespace != namespace:
            continue
        held = winners.get(record.key)
        if held is None or _precedence(record) > _precedence(held):
            winners[record.key] = record
    return [winners[k] for k in sorted(winners)]


def check_integrity(store: Store) -> list[str]:
    """Problems found: SQLite integrity checks and every indexed file's checksum (empty: fine).
    Every shard's records are checked, not only the winners; a committed file still under its
    temporary name (see `resolve_file`) is fine. A shared store: every row's files."""
    import sqlite3

    if isinstance(store, SharedStore):
        return [
            problem
            for record in _all_records(store)
            for problem in _file_problems(store.root / SHARDS_DIR / record.shard, record)
        ]
    problems = []
    for index in _shard_indexes(store):
        db = sqlite3.connect(f"file:{index}?mode=ro", uri=True)
        try:
            result = db.execute("PRAGMA integrity_check").fetchone()[0]
        finally:
            db.close()
        if result != "ok":
            problems.append(f"{index}: {result}")
        for record in read_records(index):
            problems += _file_problems(index.parent, record)
    return problems


def _file_problems(shard_dir: Path, record: StoredFrame) -> list[str]:
    problems = []
    for relative, digest in record.files.items():
        path = shard_dir / relative
        if resolve_file(shard_dir, relative, digest) is None:
            problems.append(f"{path}: {'checksum mismatch' if path.is_file() else 'missing'}")
    return problems


@dataclass(frozen=True)
class ExportSummary:
    frames: int
    train: int
    val: int
    namespaces: tuple[str, ...]


def split_of(namespace: str, frame_id: str, val_fraction: float, seed: int = 0) -> str:
    """'val' or 'train' from a hash of the key: stable, so a frame stays on its side of the
    split however the store grows (a model is never gated on frames it trained on)."""
    digest = hashlib.sha256(f"{seed}:{namespace}/{frame_id}".encode()).digest()
    return "val" if int.from_bytes(digest[:8], "big") / 2**64 < val_fraction else "train"


def export_store(
    store: Store,
    out: str | os.PathLike,
    val_fraction: float = DEFAULT_VAL_FRACTION,
    seed: int = 0,
    namespaces: Iterable[str] | None = None,
) -> ExportSummary:
    """A KITTI-layout data set of every stored frame (or those of `namespaces`): training/
    image_2, velodyne, calib, label_2 (the labels as KITTI rows), labels/ID.json,
    ImageSets/train.txt, val.txt and trainval.txt, and export.json (each exported id's
    namespace, frame id, shard, model version and split).

    Frame ids are kept when one namespace is exported, else written `<namespace>__<frame id>`
    (which must fit KITTI's 64 characters). val.txt holds the frames `split_of` puts there;
    with two or more frames and 0 < val_fraction < 1 each side gets at least one. Every copied
    file is checked against its checksum."""
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    root, out = store_files_root(store), Path(out)
    if not root.is_dir():
        raise FileNotFoundError(f"no label store at {root}")
    wanted = None if namespaces is None else set(namespaces)
    records = [r for r in list_frames(store) if wanted is None or r.namespace in wanted]
    if wanted is not None and (missing := wanted - {r.namespace for r in records}):
        raise ValueError(
            f"the store {store} holds no frame of namespace {', '.join(sorted(missing))}"
        )
    present = tuple(sorted({r.namespace for r in records}))
    names = {r.key: _export_id(r, len(present) > 1) for r in records}
    splits = {r.key: split_of(r.namespace, r.frame_id, val_fraction, seed) for r in records}
    _balance(splits, records, val_fraction, seed)
    entries = []
    for record in records:
        name = names[record.key]
        copied = _copy_frame(store, record, out, name)
        entries.append({"id": name, "namespace": copied.namespace, "frame_id": copied.frame_id,
                        "shard": copied.shard, "model_version": copied.model_version,
                        "stored_at": copied.stored_at, "split": splits[record.key]})  # fmt: skip
    train = sorted(names[k] for k, s in splits.items() if s == "train")
    val = sorted(names[k] for k, s in splits.items() if s == "val")
    write_image_set(out / "ImageSets" / "train.txt", train)
    write_image_set(out / "ImageSets" / "val.txt", val)
    write_image_set(out / "ImageSets" / "trainval.txt", sorted(train + val))
    manifest = {
        "store": str(store) if isinstance(store, SharedStore) else str(root.resolve()),
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "val_fraction": val_fraction,
        "seed": seed,
        "namespaces": list(present),
        "frames": sorted(entries, key=lambda e: e["id"]),
    }
    atomic_write_bytes(out / EXPORT_MANIFEST, (json.dumps(manifest, indent=2) + "\n").encode())
    return ExportSummary(len(records), len(train), len(val), present)


def _export_id(record: StoredFrame, prefixed: bool) -> str:
    if not prefixed:
        return record.frame_id
    name = f"{record.namespace}{NAMESPACE_SEPARATOR}{record.frame_id}"
    if not FRAME_ID_PATTERN.match(name):
        raise ValueError(
            f"exported id {name!r} exceeds 64 characters; export one namespace at a time "
            "(--namespace) to keep bare frame ids"
        )
    return name


def _balance(
    splits: dict[tuple[str, str], str], records: list[StoredFrame], fraction: float, seed: int
) -> None:
    """At least one frame on each side when there are two or more and 0 < fraction: the
    frame whose hash is nearest the other side moves."""
    if len(records) < 2 or fraction <= 0.0:
        return

    def position(record: StoredFrame) -> bytes:
        return hashlib.sha256(f"{seed}:{record.namespace}/{record.frame_id}".encode()).digest()

    for side, pick in (("val", min), ("train", max)):
        if side not in splits.values():
            splits[pick(records, key=position).key] = side


def read_frame(
    store: Store, record: StoredFrame, kinds: Iterable[str] | None = None
) -> tuple[StoredFrame, dict[str, bytes]]:
    """A stored frame's files (path relative to its shard -> bytes; only those of `kinds`,
    store_layout.FRAME_FILES' names, when given), each checked against its checksum; a
    mismatch (a replacement in flight) re-reads the record. Returns the record the files are
    of."""
    root = store_files_root(store)
    wanted = None if kinds is None else tuple(
        f"{FRAME_FILES[kind][0]}/{record.frame_id}{FRAME_FILES[kind][1]}" for kind in kinds
    )  # fmt: skip
    for _ in range(READ_RETRIES):
        contents = {}
        for relative, digest in record.files.items():
            if wanted is not None and not relative.endswith(wanted):
                continue
            path = resolve_file(root / SHARDS_DIR / record.shard, relative, digest)
            try:
                data = None if path is None else path.read_bytes()
            except FileNotFoundError:  # renamed in the meantime
                data = None
            if data is None or hashlib.sha256(data).hexdigest() != digest:
                break
            contents[relative] = data
        else:
            return record, contents
        time.sleep(0.05)
        fresh = [r for r in list_frames(store, record.namespace) if r.key == record.key]
        record = fresh[0] if fresh else record
    raise ValueError(
        f"frame {record.namespace}/{record.frame_id} of shard {record.shard}: its files do not "
        "match its checksums; run `detmatch serve` on that shard once to recover it"
    )


def _copy_frame(store: Store, record: StoredFrame, out: Path, name: str) -> StoredFrame:
    """Copy a frame's files under its exported name, each checked against its checksum."""
    record, contents = read_frame(store, record)
    for relative, data in contents.items():
        inner = Path(relative)  # namespaces/<ns>/<dir>/<file>; schema 1: <dir>/<file>
        if inner.parts[0] == NAMESPACES_DIR:
            inner = Path(*inner.parts[2:])
        atomic_write_bytes(out / inner.parent / f"{name}{inner.suffix}", data)
    return record
