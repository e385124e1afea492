"""What a retraining round read from the label store, identified by content.

A store snapshot id is the SHA-256 of the sorted content digests of every stored frame, a
frame's digest being the SHA-256 of its files' sorted SHA-256s. It depends only on what is
stored, not on shard names, frame ids or when frames arrived, so it comes out the same from
the store's index (`store_snapshot`: cheap, the index lists every file's SHA-256) and from the
files an export copied (`frame_digest` of their digests). A round records the id of what it
trained on; the scheduler skips a round while the store's id has not changed.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from serving.reviews import read_human_labels, review_digest
from serving.store import list_frames
from serving.store_export import Store
from serving.store_index import SharedStore


def frame_digest(file_digests: Iterable[str]) -> str:
    """One frame's content digest from its files' hex SHA-256s (in any order)."""
    return hashlib.sha256("\n".join(sorted(file_digests)).encode()).hexdigest()


def snapshot_id(frame_digests: Iterable[str]) -> str:
    """A set of frames' id from their content digests (in any order)."""
    return hashlib.sha256("\n".join(sorted(frame_digests)).encode()).hexdigest()


@dataclass(frozen=True)
class StoreSnapshot:
    id: str
    frames: int


def store_snapshot(store: Store) -> StoreSnapshot:
    """The id and frame count of everything a label store holds now (every shard; or a shared
    store's index)."""
    if not isinstance(store, SharedStore) and not Path(store).is_dir():
        raise FileNotFoundError(f"no label store at {store}")
    records = list_frames(store)
    reviews = read_human_labels(store)
    return StoreSnapshot(
        snapshot_id(frame_digest(stored_digests(r.files.values(), reviews.get(r.key)))
                    for r in records),
        len(records),
    )  # fmt: skip


def stored_digests(file_digests: Iterable[str], review: dict | None) -> list[str]:
    """What identifies a stored frame's content: its files' digests, and its human labels'
    when it was reviewed (a new review is new data for the next round)."""
    digests = list(file_digests)
    return digests if review is None else [*digests, review_digest(review)]
