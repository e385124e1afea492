"""A label store index in PostgreSQL, shared by every replica (`--store postgresql://...
--store-root DIR`; the `postgres` extra, psycopg 3).

One row per key (namespace, frame id) for the whole store, naming the shard whose files hold
the key's labels. Each replica keeps writing its own shard's files under the shared root (one
process per shard, as in the embedded store), so no two processes ever write the same file;
what they share is the row. A batch of puts takes a transaction-scoped advisory lock on
each of its keys (in sorted order: no deadlock between two replicas' batches), reads the
keys' rows, and writes the new ones; the commit is the commit point, exactly as the SQLite
row is in the embedded store. So the same frame sent to two replicas at once is stored once:
one replica's put CREATES it, the other's is UNCHANGED (the same labels) or REPLACES it.
Files of a key whose row another replica took over stay in the old shard until that shard's
replica opens it again (opening deletes every file no row of its shard lists).

Schema versions are applied in order, under an advisory lock, in one transaction each
(`MIGRATIONS`); a server refuses an index newer than it knows. The root is tied to the index:
the first open writes the index's store id into ROOT/store-id, and a replica whose root holds
another store's id (the wrong volume mounted) is refused.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from serving.errors import StoreError
from serving.store_index import Key, LockedRows, SharedStore, mask_url
from serving.store_layout import COLUMNS, INDEX_FILE, SHARDS_DIR, StoredFrame, record_of

ROOT_ID_FILE = "store-id"
CONNECT_TIMEOUT_S = 10
# Any constant: the lock under which migrations run.
MIGRATION_LOCK = 0x6465746D61746368  # "detmatch"
MIGRATIONS = {
    1: [
        """CREATE TABLE detmatch_meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)""",
        """CREATE TABLE detmatch_frames (
            namespace TEXT NOT NULL,
            frame_id TEXT NOT NULL,
            model_version TEXT NOT NULL,
            stored_at DOUBLE PRECISION NOT NULL,
            first_stored_at DOUBLE PRECISION NOT NULL,
            num_labels INTEGER NOT NULL,
            num_matched INTEGER NOT NULL,
            num_lidar_only INTEGER NOT NULL,
            provenance TEXT NOT NULL,
            files TEXT NOT NULL,
            shard TEXT NOT NULL,
            PRIMARY KEY (namespace, frame_id)
        )""",
        "CREATE INDEX detmatch_frames_shard ON detmatch_frames (shard)",
    ],
}
SCHEMA_VERSION = max(MIGRATIONS)
SELECT = f"SELECT {', '.join(COLUMNS)}, shard FROM detmatch_frames"
UPSERT = (
    f"INSERT INTO detmatch_frames ({', '.join(COLUMNS)}, shard) "
    f"VALUES ({', '.join(['%s'] * (len(COLUMNS) + 1))}) "
    "ON CONFLICT (namespace, frame_id) DO UPDATE SET "
    + ", ".join(f"{c} = EXCLUDED.{c}" for c in (*COLUMNS[2:], "shard"))
)


def _psycopg():
    try:
        import psycopg
    except ImportError:
        raise StoreError(
            "a postgresql:// label store needs psycopg: pip install 'detmatch[postgres]'"
        ) from None
    return psycopg


def connect(url: str):
    """A connection (autocommit) or StoreError naming the URL, its password masked."""
    psycopg = _psycopg()
    try:
        return psycopg.connect(url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S)
    except psycopg.Error as error:
        reason = str(error).strip().splitlines()[-1] if str(error).strip() else type(error)
        raise StoreError(f"cannot open the label store index {mask_url(url)}: {reason}") from None


class PostgresIndex:
    """The shared index, as `serving.store_index.Index`; thread-safe (one connection for
    reads, one for the committer's transactions)."""

    def __init__(self, store: SharedStore) -> None:
        self.store = store
        self._reader = connect(store.url)
        try:
            self._writer = connect(store.url)
        except BaseException:
            self._reader.close()
            raise
        self._read_lock, self._write_lock = threading.Lock(), threading.Lock()
        try:
            store_id = migrate(self._writer)
            tie_root(store.root, store_id)
        except BaseException:
            self.close()
            raise

    def shard_records(self, shard: str) -> list[StoredFrame]:
        return self._read(f"{SELECT} WHERE shard = %s", (shard,))

    def get(self, key: Key) -> StoredFrame | None:
        rows = self._read(f"{SELECT} WHERE namespace = %s AND frame_id = %s", key)
        return rows[0] if rows else None

    def _read(self, query: str, parameters: tuple) -> list[StoredFrame]:
        with self._read_lock:
            return _rows(self._reader, query, parameters, self.store)

    @contextmanager
    def locked(self, keys: Iterable[Key]) -> Iterator[LockedRows]:
        psycopg = _psycopg()
        keys = sorted(set(keys))
        with self._write_lock:
            try:
                with self._writer.transaction():
                    for namespace, frame_id in keys:
                        self._writer.execute(
                            "SELECT pg_advisory_xact_lock(hashtextextended(%s, 0))",
                            (f"{namespace}/{frame_id}",),
                        )
                    current: dict[Key, StoredFrame | None] = dict.fromkeys(keys)
                    for record in _rows(
                        self._writer,
                        f"{SELECT} WHERE (namespace, frame_id) IN "
                        f"({', '.join(['(%s, %s)'] * len(keys))})",
                        tuple(part for key in keys for part in key),
                        self.store,
                    ):
                        current[record.key] = record
                    rows = LockedRows(current)
                    yield rows
                    if rows.writes:
                        with self._writer.cursor() as cursor:
                            cursor.executemany(UPSERT, [(*r.row(), r.shard) for r in rows.writes])
            except psycopg.Error as error:
                raise StoreError(f"index {mask_url(self.store.url)}: {error}") from error

    def close(self) -> None:
        for connection in (getattr(self, "_reader", None), getattr(self, "_writer", None)):
            if connection is not None:
                connection.close()


def migrate(connection) -> str:
    """Bring the index to SCHEMA_VERSION (each version in its own transaction, under an
    advisory lock, so replicas starting at once migrate once); its store id."""
    with connection.transaction():
        connection.execute("SELECT pg_advisory_xact_lock(%s)", (MIGRATION_LOCK,))
        exists = connection.execute("SELECT to_regclass('detmatch_meta')").fetchone()[0]
        version = 0
        if exists is not None:
            row = connection.execute(
                "SELECT value FROM detmatch_meta WHERE key = 'schema_version'"
            ).fetchone()
            version = int(row[0]) if row else 0
        if version > SCHEMA_VERSION:
            raise StoreError(
                f"label store index schema {version}; this version of detmatch knows "
                f"<= {SCHEMA_VERSION}: upgrade it"
            )
        for step in range(version + 1, SCHEMA_VERSION + 1):
            for statement in MIGRATIONS[step]:
                connection.execute(statement)
            connection.execute(
                "INSERT INTO detmatch_meta VALUES ('schema_version', %s) "
                "ON CONFLICT (key) DO UPDATE SET value = EXCLUDED.value",
                (str(step),),
            )
        connection.execute(
            "INSERT INTO detmatch_meta VALUES ('store_id', %s) ON CONFLICT (key) DO NOTHING",
            (uuid.uuid4().hex,),
        )
        return connection.execute(
            "SELECT value FROM detmatch_meta WHERE key = 'store_id'"
        ).fetchone()[0]


def tie_root(root: Path, store_id: str) -> None:
    """ROOT/store-id names the index whose files the root holds: written on the first open,
    checked on every other; an embedded store's root (SQLite shard indexes) is refused."""
    marker = root / ROOT_ID_FILE
    if marker.is_file():
        held = marker.read_text().strip()
        if held != store_id:
            raise StoreError(
                f"{root} holds the files of another label store (store id {held}, this "
                f"index's is {store_id}): mount the volume this index was created with"
            )
        return
    if any((root / SHARDS_DIR).glob(f"*/{INDEX_FILE}")):
        raise StoreError(
            f"{root} holds an embedded label store (SQLite shard indexes): give a PostgreSQL "
            "store a root of its own"
        )
    try:
        root.mkdir(parents=True, exist_ok=True)
        temporary = root / f".{ROOT_ID_FILE}.{uuid.uuid4().hex[:8]}.tmp"
        temporary.write_text(store_id + "\n")
        temporary.replace(marker)
    except OSError as error:
        raise StoreError(f"cannot write the label store's files at {root}: {error}") from None


def read_all(store: SharedStore) -> list[StoredFrame]:
    """Every row of a shared store's index, sorted by key (listing, export, snapshots); the
    index must exist (a store no replica has opened yet holds nothing)."""
    connection = connect(store.url)
    try:
        if connection.execute("SELECT to_regclass('detmatch_frames')").fetchone()[0] is None:
            return []
        return _rows(connection, f"{SELECT} ORDER BY namespace, frame_id", (), store)
    finally:
        connection.close()


def _rows(connection, query: str, parameters: tuple, store: SharedStore) -> list[StoredFrame]:
    psycopg = _psycopg()
    try:
        rows = connection.execute(query, parameters).fetchall()
    except psycopg.Error as error:
        raise StoreError(f"index {mask_url(store.url)}: {error}") from error
    return [record_of(r[:-1], r[-1]) for r in rows]
