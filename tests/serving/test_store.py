"""The label store: layout, the re-labeling policy, namespaces, shards, export (train/val
ImageSets), migration of schema 1, crash recovery and the shard lock (through the server:
tests/grpc_service/test_store_over_grpc.py)."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import sqlite3
import threading
from pathlib import Path

import numpy as np
import pytest

from commands.main import main
from detmatch.data.kitti import KittiDataset, read_image_set, read_objects
from serving.errors import StoreError
from serving.store import (
    LabelStore,
    StoreOutcome,
    check_integrity,
    export_store,
    list_frames,
)
from serving.store_layout import frame_paths, sha256
from tests.conftest import KITTI_SAMPLE
from tests.serving.store_helpers import (
    labels_of,
    listed_files,
    put_frame,
    shard_files,
)


def test_put_creates_then_a_retry_is_unchanged_in_wal_mode(tmp_path, served_labeler):
    store = LabelStore(tmp_path, "a")
    first = put_frame(store, served_labeler, "f1")
    again = put_frame(store, served_labeler, "f1")
    assert first.outcome == StoreOutcome.CREATED and first.previous_version is None
    assert again.outcome == StoreOutcome.UNCHANGED and again.record == first.record
    assert again.previous_version == served_labeler.version
    assert store.get("f1") == first.record and store.get("f2") is None
    store.close()
    db = sqlite3.connect(tmp_path / "shards" / "a" / "index.sqlite")
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert db.execute("SELECT COUNT(*) FROM frames").fetchone()[0] == 1
    db.close()
    assert check_integrity(tmp_path) == []
    assert shard_files(tmp_path) == listed_files(tmp_path)


def test_a_relabel_by_another_version_replaces_and_says_so(tmp_path, served_labeler):
    """Defect 8: after a model swap a re-label answered `stored: true` with the new labels
    while the store kept the old ones. Policy: the latest labeling replaces."""
    store = LabelStore(tmp_path, "a")
    png, frame, result = labels_of(served_labeler)
    created = store.put("f1", png, frame.points, frame.calib, result)
    newer = dataclasses.replace(result, model_version="000002")
    replaced = store.put("f1", png, frame.points, frame.calib, newer)
    assert replaced.outcome == StoreOutcome.REPLACED
    assert replaced.previous_version == result.model_version
    assert replaced.record.model_version == "000002"
    assert replaced.record.first_stored_at == created.record.first_stored_at
    other_frame = put_frame(store, served_labeler, "f1", source="000001")  # other data, same key
    assert other_frame.outcome == StoreOutcome.REPLACED
    store.close()
    (record,) = list_frames(tmp_path)
    assert record.model_version == served_labeler.version
    stored = json.loads((tmp_path / "shards" / "a" / frame_paths("default", "f1")["labels"])
                        .read_text())  # fmt: skip
    assert stored["model_version"] == served_labeler.version
    exported = KittiDataset(tmp_path / "shards" / "a" / "namespaces" / "default")
    source = KittiDataset(KITTI_SAMPLE).load_frame("000001", with_labels=False)
    np.testing.assert_array_equal(exported.load_frame("f1").points, source.points)
    assert check_integrity(tmp_path) == []
    assert shard_files(tmp_path) == listed_files(tmp_path)


@pytest.mark.parametrize("frame_id", ["../x", "a/b", "..", "/etc/passwd", "a" * 65, "x\0y", ""])
def test_frame_ids_cannot_escape_the_store(tmp_path, served_labeler, frame_id):
    store = LabelStore(tmp_path / "store", "a")
    with pytest.raises(ValueError, match="invalid frame id"):
        put_frame(store, served_labeler, frame_id)
    with pytest.raises(ValueError, match="invalid namespace"):
        put_frame(store, served_labeler, "ok", namespace=frame_id)
    store.close()
    assert shard_files(tmp_path / "store") == set()
    with pytest.raises(ValueError, match="invalid shard"):
        LabelStore(tmp_path / "store", "../other")


def test_shards_and_namespaces_are_exported_with_train_and_val_sets(
    tmp_path, served_labeler, capsys
):
    first, second = LabelStore(tmp_path / "store", "a"), LabelStore(tmp_path / "store", "b")
    for i in range(12):
        put_frame(first, served_labeler, f"f{i:02d}", source=f"00000{i % 3}")
    put_frame(second, served_labeler, "f01", source="000001")  # the same key on two replicas
    put_frame(second, served_labeler, "f01", source="000002", namespace="site-b")
    first.close()
    second.close()
    records = list_frames(tmp_path / "store")
    assert len(records) == 13
    winner = [r for r in records if r.key == ("default", "f01")][0]
    assert winner.shard == "b"  # the latest labeling of a key wins
    out = tmp_path / "out"
    assert main(["store", "export", "--store", str(tmp_path / "store"), "--out", str(out),
                 "--val-fraction", "0.25"]) == 0  # fmt: skip
    assert "exported 13 stored frames" in capsys.readouterr().out
    train = read_image_set(out / "ImageSets" / "train.txt")
    val = read_image_set(out / "ImageSets" / "val.txt")
    assert val and train and not set(train) & set(val)
    assert sorted(train + val) == read_image_set(out / "ImageSets" / "trainval.txt")
    assert "site-b__f01" in train + val and "default__f01" in train + val
    manifest = json.loads((out / "export.json").read_text())
    assert {e["id"]: e["split"] for e in manifest["frames"]}["site-b__f01"] in ("train", "val")
    exported = KittiDataset(out).load_frame("site-b__f01", with_labels=False)
    source = KittiDataset(KITTI_SAMPLE).load_frame("000002", with_labels=False)
    np.testing.assert_array_equal(exported.points, source.points)
    np.testing.assert_allclose(exported.calib.P2, source.calib.P2)
    rows = out / "training" / "label_2" / "default__f01.txt"
    objects = read_objects(rows)
    # The winner's rows, byte for byte: its labels whose 3D centre projects into the image.
    assert sha256(rows.read_bytes()) == winner.files[frame_paths("default", "f01")["label_2"]]
    assert 0 < len(objects) <= winner.num_labels and objects.score is not None
    assert (out / "labels" / "default__f01.json").is_file()
    again = tmp_path / "again"
    export_store(tmp_path / "store", again, val_fraction=0.25)
    assert read_image_set(again / "ImageSets" / "val.txt") == val  # deterministic
    one = export_store(tmp_path / "store", tmp_path / "one", namespaces=["default"])
    assert one.frames == 12 and one.namespaces == ("default",)
    assert (tmp_path / "one" / "training" / "velodyne" / "f05.bin").is_file()  # bare ids


def test_an_export_is_a_data_set_training_reads(tmp_path, served_labeler):
    """`detmatch train --data EXPORT` reads exactly this: FrameDataset over train and val."""
    from detmatch.config import load_config
    from detmatch.data.dataset import FrameDataset
    from detmatch.models.detector3d import pillar_grid
    from tests.conftest import REPO

    store = LabelStore(tmp_path / "store", "a")
    for i in range(6):
        put_frame(store, served_labeler, f"k{i}", source=f"00000{i % 3}", namespace="kitti")
    store.close()
    summary = export_store(tmp_path / "store", tmp_path / "out", val_fraction=0.3)
    assert summary.train + summary.val == 6 and summary.val >= 1
    config = load_config(REPO / "configs" / "tiny.toml")
    grid = pillar_grid(config.detector3d)
    for split in ("train", "val"):
        dataset = FrameDataset(tmp_path / "out", split, config.data.classes,
                               config.data.image_size, grid)  # fmt: skip
        samples = [dataset[i] for i in range(len(dataset))]
        assert len(samples) == (summary.train if split == "train" else summary.val)


def test_schema_1_stores_are_migrated_on_open_and_say_so(tmp_path, served_labeler, caplog):
    """A store written before namespaces (rows keyed by the bare id, files at
    shards/<shard>/training/...) opens: files move under namespace 'default', rows gain it."""
    root = tmp_path / "store"
    store = LabelStore(root, "old")
    for frame_id, source in (("f1", "000000"), ("f2", "000001")):
        put_frame(store, served_labeler, frame_id, source=source)
    store.close()
    shard = root / "shards" / "old"
    _downgrade_to_schema_1(shard)
    (shard / "training" / "velodyne" / "f9.bin").write_bytes(b"\0" * 16)  # old debris
    assert {(r.namespace, r.frame_id) for r in list_frames(root)} == {
        ("default", "f1"),
        ("default", "f2"),
    }  # readers read schema 1 as it is
    assert check_integrity(root) == []
    assert export_store(root, tmp_path / "before").frames == 2
    assert (tmp_path / "before" / "training" / "velodyne" / "f2.bin").is_file()
    with caplog.at_level(logging.INFO, logger="detmatch.serving"):
        store = LabelStore(root, "old")
    assert "label store migrated" in caplog.text
    migrated = [r for r in caplog.records if r.getMessage() == "label store migrated"][0]
    assert migrated.fields["frames"] == 2 and migrated.fields["from_schema"] == 1
    assert set(store.get("f1").files) == set(frame_paths("default", "f1").values())
    assert put_frame(store, served_labeler, "f1").outcome == StoreOutcome.UNCHANGED
    store.close()
    assert not (shard / "training").exists()
    assert check_integrity(root) == []
    assert shard_files(root) == listed_files(root)


def _downgrade_to_schema_1(shard: Path) -> None:
    """Rewrite a shard as the store before namespaces wrote it."""
    db = sqlite3.connect(shard / "index.sqlite")
    rows = db.execute(
        "SELECT frame_id, model_version, stored_at, num_labels, num_matched, num_lidar_only, "
        "provenance, files FROM frames"
    ).fetchall()
    db.execute("DROP TABLE frames")
    db.execute("PRAGMA user_version = 0")
    db.execute(
        "CREATE TABLE frames (frame_id TEXT PRIMARY KEY, model_version TEXT NOT NULL, "
        "stored_at REAL NOT NULL, num_labels INTEGER NOT NULL, num_matched INTEGER NOT NULL, "
        "num_lidar_only INTEGER NOT NULL, provenance TEXT NOT NULL, files TEXT NOT NULL)"
    )
    for row in rows:
        files = {k.split("/", 2)[2]: v for k, v in json.loads(row[7]).items()}
        db.execute("INSERT INTO frames VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                   (*row[:7], json.dumps(files)))  # fmt: skip
    db.commit()
    db.close()
    namespace = shard / "namespaces" / "default"
    for directory in ("training", "labels"):
        shutil.move(namespace / directory, shard / directory)
    shutil.rmtree(shard / "namespaces")


def test_opening_a_shard_removes_crash_debris_and_finishes_replacements(
    tmp_path, served_labeler, caplog
):
    """Defect 7: a killed writer leaves temporary files and files without an index row (the
    24-SIGKILL run left 9 and 44-53). Opening the shard deletes them, rolls a replacement
    whose row committed forward, and logs the counts."""
    root = tmp_path / "store"
    store = LabelStore(root, "s0")
    put_frame(store, served_labeler, "kept")
    store.close()
    shard = root / "shards" / "s0"
    paths = frame_paths("default", "kept")
    # A frame killed before its commit: every file in place, no row.
    for kind, relative in frame_paths("default", "orphan").items():
        (shard / relative).write_bytes((shard / paths[kind]).read_bytes())
    # Temporary files of killed writes.
    for relative in list(paths.values())[:3]:
        target = shard / relative
        target.with_name(f".{target.name}.dead01.tmp").write_bytes(b"half")
    # A replacement killed after its commit: the row lists the new labels, still a temp file.
    labels = shard / paths["labels"]
    new_labels = labels.read_bytes().replace(b'"frame_id"', b'"frame_id" ', 1)
    labels.with_name(f".{labels.name}.abc123.tmp").write_bytes(new_labels)
    db = sqlite3.connect(shard / "index.sqlite")
    files = json.loads(db.execute("SELECT files FROM frames").fetchone()[0])
    from hashlib import sha256

    files[paths["labels"]] = sha256(new_labels).hexdigest()
    db.execute("UPDATE frames SET files = ?", (json.dumps(files),))
    db.commit()
    db.close()
    assert labels.read_bytes() != new_labels  # the committed labels are still a temp file ...
    assert check_integrity(root) == []  # ... which readers find by its checksum
    with caplog.at_level(logging.INFO, logger="detmatch.serving"):
        store = LabelStore(root, "s0")
    opened = [r for r in caplog.records if r.getMessage() == "label store opened"][-1]
    assert (opened.fields["temporary_removed"], opened.fields["rolled_forward"],
            opened.fields["orphans_removed"]) == (3, 1, 5)  # fmt: skip
    assert store.get("orphan") is None
    store.close()
    assert check_integrity(root) == []
    assert labels.read_bytes() == new_labels
    assert shard_files(root) == listed_files(root)


def test_a_shard_is_written_by_one_process_at_a_time(tmp_path):
    store = LabelStore(tmp_path, "a")
    with pytest.raises(StoreError, match="shard a .* is open in another process"):
        LabelStore(tmp_path, "a")
    store.close()
    LabelStore(tmp_path, "a").close()


def test_concurrent_puts_are_committed_in_groups(tmp_path, served_labeler):
    """Many threads at once: every frame stored, integrity intact, fewer commits than frames
    is possible (group commit) and never more."""
    store = LabelStore(tmp_path, "a")
    png, frame, result = labels_of(served_labeler)
    outcomes = []

    def put(i: int) -> None:
        outcomes.append(store.put(f"c{i:03d}", png, frame.points, frame.calib, result).outcome)

    threads = [threading.Thread(target=put, args=(i,)) for i in range(24)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert outcomes == [StoreOutcome.CREATED] * 24
    assert store.stats.frames == 24 and 1 <= store.stats.batches <= 24
    store.close()
    assert len(list_frames(tmp_path)) == 24 and check_integrity(tmp_path) == []
