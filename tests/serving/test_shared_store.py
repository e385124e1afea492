"""The shared label store (PostgreSQL index, files under a root every replica mounts): the
re-labeling policy across replicas, many writers of the same keys at once, listing, export
and snapshots through the embedded store's interface, and clear refusals at start (a
server's SIGKILLs: tests/grpc_service/test_shared_store_over_grpc.py)."""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import pytest

from retrain.snapshot import store_snapshot
from serving.errors import StoreError
from serving.store import LabelStore, StoreOutcome, check_integrity, export_store, list_frames
from serving.store_index import SharedStore, mask_url, store_location
from tests.postgres import postgres_server, postgres_url  # noqa: F401 - fixtures
from tests.serving.store_helpers import labels_of


@pytest.fixture
def shared(tmp_path, postgres_url) -> SharedStore:  # noqa: F811
    return SharedStore(postgres_url, tmp_path / "root")


def test_two_replicas_store_one_label_per_key_by_the_relabel_rule(shared, served_labeler):
    png, frame, result = labels_of(served_labeler)
    with LabelStore(shared, "a") as a, LabelStore(shared, "b") as b:
        created = a.put("f1", png, frame.points, frame.calib, result)
        retry = b.put("f1", png, frame.points, frame.calib, result)
        assert created.outcome == StoreOutcome.CREATED
        assert retry.outcome == StoreOutcome.UNCHANGED and retry.record == created.record
        assert retry.record.shard == "a"  # b wrote nothing
        newer = dataclasses.replace(result, model_version="000002")
        replaced = b.put("f1", png, frame.points, frame.calib, newer)
        assert replaced.outcome == StoreOutcome.REPLACED
        assert replaced.previous_version == result.model_version
        assert replaced.record.first_stored_at == created.record.first_stored_at
        assert a.get("f1") == b.get("f1") == replaced.record
        other = a.put("f2", png, frame.points, frame.calib, result, namespace="site-b")
        assert other.outcome == StoreOutcome.CREATED
    records = list_frames(shared)
    assert [(r.namespace, r.frame_id, r.shard, r.model_version) for r in records] == [
        ("default", "f1", "b", "000002"),
        ("site-b", "f2", "a", result.model_version),
    ]
    assert check_integrity(shared) == []
    summary = export_store(shared, shared.root.parent / "export", val_fraction=0.5)
    assert summary.frames == 2 and summary.namespaces == ("default", "site-b")
    snapshot = store_snapshot(shared)
    assert snapshot.frames == 2
    # the replaced labels' files stay in shard a until a reopens it; then they are gone
    assert (shared.root / "shards" / "a" / "namespaces" / "default").is_dir()
    LabelStore(shared, "a").close()
    assert not list((shared.root / "shards" / "a" / "namespaces" / "default").rglob("f1*"))
    assert check_integrity(shared) == [] and store_snapshot(shared) == snapshot


def test_replicas_writing_the_same_keys_at_once_create_each_once(shared, served_labeler):
    png, frame, result = labels_of(served_labeler)
    versions = [dataclasses.replace(result, model_version=f"{v:06d}") for v in (1, 2)]
    outcomes: list[tuple[str, StoreOutcome]] = []
    errors: list[BaseException] = []
    stores = [LabelStore(shared, "a"), LabelStore(shared, "b")]

    def write(store: LabelStore, labels) -> None:
        try:
            for i in range(12):
                put = store.put(f"k{i:02d}", png, frame.points, frame.calib, labels)
                outcomes.append((f"k{i:02d}", put.outcome))
        except BaseException as error:  # noqa: BLE001 - reported below
            errors.append(error)

    threads = [
        threading.Thread(target=write, args=(store, labels))
        for store in stores
        for labels in versions
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    for store in stores:
        store.close()
    assert not errors and len(outcomes) == 4 * 12
    for i in range(12):
        mine = [o for key, o in outcomes if key == f"k{i:02d}"]
        assert mine.count(StoreOutcome.CREATED) == 1, mine
    records = list_frames(shared)
    assert len(records) == 12
    assert {r.model_version for r in records} <= {"000001", "000002"}
    assert check_integrity(shared) == []


def test_a_bad_index_or_root_is_refused_at_start_naming_it(shared, tmp_path, postgres_url):  # noqa: F811
    user_and_password = postgres_url.split("://", 1)[1].split("@", 1)[0]
    password = user_and_password.split(":", 1)[1]
    wrong = postgres_url.replace(f":{password}@", ":not-the-password@")
    with pytest.raises(StoreError, match="cannot open the label store index") as caught:
        LabelStore(SharedStore(wrong, shared.root), "a")
    assert "not-the-password" not in str(caught.value) and ":***@" in str(caught.value)
    closed = "postgresql://u:secret@127.0.0.1:1/db"
    with pytest.raises(StoreError, match=r"postgresql://u:\*\*\*@127\.0\.0\.1:1/db"):
        LabelStore(SharedStore(closed, shared.root), "a")

    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    with pytest.raises(StoreError, match="cannot write the label store's files"):
        LabelStore(SharedStore(postgres_url, blocker / "root"), "a")

    LabelStore(shared, "a").close()  # ties the root to this index
    other = tmp_path / "other-root"
    (other).mkdir()
    (other / "store-id").write_text("0" * 32 + "\n")
    with pytest.raises(StoreError, match="holds the files of another label store"):
        LabelStore(SharedStore(postgres_url, other), "a")

    embedded = tmp_path / "embedded"
    LabelStore(embedded, "a").close()
    with pytest.raises(StoreError, match="holds an embedded label store"):
        LabelStore(SharedStore(postgres_url, embedded), "a")


def test_an_index_newer_than_this_version_is_refused(shared):
    import psycopg

    LabelStore(shared, "a").close()
    with psycopg.connect(shared.url, autocommit=True) as connection:
        connection.execute("UPDATE detmatch_meta SET value = '99' WHERE key = 'schema_version'")
    with pytest.raises(StoreError, match="schema 99"):
        LabelStore(shared, "a")


def test_store_options_and_masking():
    assert store_location("some/dir") == Path("some/dir")
    location = store_location("postgresql://u:pw@h:5432/db", "/mnt/labels")
    assert location == SharedStore("postgresql://u:pw@h:5432/db", Path("/mnt/labels"))
    assert "pw" not in str(location) and "/mnt/labels" in str(location)
    with pytest.raises(ValueError, match="needs --store-root"):
        store_location("postgres://u:pw@h/db")
    with pytest.raises(ValueError, match="postgresql:// --store only"):
        store_location("some/dir", "/mnt/labels")
    assert mask_url("postgresql://u@h/db") == "postgresql://u@h/db"
    assert mask_url("postgresql://h/db?password=pw&x=1") == "postgresql://h/db?password=***&x=1"
