"""A label store's index: where the rows live that say which labels are stored.

`LabelStore` keeps its files the same way whichever index it has; the index is
- `SqliteIndex` (the embedded default): one SQLite file per shard, written by the shard's
  one process (`serving.store_layout`);
- `serving.store_postgres.PostgresIndex`: one PostgreSQL table shared by every replica, each
  replica still writing its own shard's files under a root they all mount.

Both give `LabelStore` the same three things: the rows of its own shard (what opening it
repairs files against), one key's row, and `locked(keys)`: the current rows of a batch's
keys, read and rewritten atomically with respect to every other writer of the index, so
the re-labeling policy's outcome (created / unchanged / replaced) is decided on the row
that is really there.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from serving.errors import StoreError
from serving.store_layout import COLUMNS, StoredFrame, open_index, record_of, transaction

Key = tuple[str, str]  # (namespace, frame id)


@dataclass
class LockedRows:
    """The rows of a batch's keys as they are while the index is locked (None: no row), and
    the rows to write before the lock is released."""

    current: dict[Key, StoredFrame | None]
    writes: list[StoredFrame] = field(default_factory=list)


class Index(Protocol):
    def shard_records(self, shard: str) -> list[StoredFrame]: ...

    def get(self, key: Key) -> StoredFrame | None: ...

    def locked(self, keys: Iterable[Key]) -> Iterator[LockedRows]: ...

    def close(self) -> None: ...


class SqliteIndex:
    """One shard's SQLite index (WAL, synchronous=FULL), thread-safe."""

    SELECT = f"SELECT {', '.join(COLUMNS)} FROM frames WHERE namespace = ? AND frame_id = ?"
    UPSERT = f"INSERT OR REPLACE INTO frames VALUES ({', '.join('?' * len(COLUMNS))})"

    def __init__(self, shard_dir: Path) -> None:
        self.shard = shard_dir.name
        self._db = open_index(shard_dir)
        self._lock = threading.Lock()

    def shard_records(self, shard: str) -> list[StoredFrame]:
        with self._lock:
            rows = self._db.execute(f"SELECT {', '.join(COLUMNS)} FROM frames").fetchall()
        return [record_of(r, self.shard) for r in rows]

    def get(self, key: Key) -> StoredFrame | None:
        with self._lock:
            row = self._db.execute(self.SELECT, key).fetchone()
        return None if row is None else record_of(row, self.shard)

    @contextmanager
    def locked(self, keys: Iterable[Key]) -> Iterator[LockedRows]:
        with self._lock:
            current = {}
            for key in set(keys):
                row = self._db.execute(self.SELECT, key).fetchone()
                current[key] = None if row is None else record_of(row, self.shard)
            rows = LockedRows(current)
            yield rows
            try:
                with transaction(self._db):
                    self._db.executemany(self.UPSERT, [r.row() for r in rows.writes])
            except sqlite3.Error as error:
                raise StoreError(f"index: {error}") from error

    def close(self) -> None:
        with self._lock:
            self._db.close()


POSTGRES_SCHEMES = ("postgresql://", "postgres://")


@dataclass(frozen=True)
class SharedStore:
    """A label store shared by replicas: its index in PostgreSQL (url), its files under root,
    a directory every replica mounts at the same path."""

    url: str
    root: Path

    def __str__(self) -> str:
        return f"{mask_url(self.url)} (files under {self.root})"


def is_index_url(store: str | Path) -> bool:
    return str(store).startswith(POSTGRES_SCHEMES)


def store_location(store: str | Path, root: str | Path | None = None) -> Path | SharedStore:
    """What `--store` (and `--store-root`) name: a directory (the embedded store) or, for a
    postgresql:// URL, a SharedStore, whose files need a root."""
    if is_index_url(store):
        if root is None:
            raise ValueError(
                f"--store {mask_url(str(store))}: a PostgreSQL index needs --store-root, the "
                "directory every replica mounts for the frames' files"
            )
        return SharedStore(str(store), Path(root))
    if root is not None:
        raise ValueError("--store-root goes with a postgresql:// --store only")
    return Path(store)


def store_files_root(location: str | Path | SharedStore) -> Path:
    """The directory holding a store's shards' files."""
    return location.root if isinstance(location, SharedStore) else Path(location)


def mask_url(url: str) -> str:
    """The URL with its password replaced by ***: safe to print and log."""
    scheme, sep, rest = url.partition("://")
    credentials, at, host = rest.rpartition("@")
    if not at or ":" not in credentials:
        masked = url
    else:
        masked = f"{scheme}{sep}{credentials.split(':', 1)[0]}:***@{host}"
    if "password=" in masked:
        import re

        masked = re.sub(r"password=[^&\s]*", "password=***", masked)
    return masked
