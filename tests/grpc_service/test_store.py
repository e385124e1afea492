"""The label store: layout, idempotency, shards, export, traversal, and a killed server."""

from __future__ import annotations

import signal
import sqlite3
import threading
import time

import grpc
import numpy as np
import pytest

from detmatch.cli import main
from detmatch.data.kitti import KittiDataset, read_image_set, read_objects
from serving.client import LabelingClient
from serving.store import LabelStore, check_integrity, list_frames
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import serve_process


def _put(store: LabelStore, labeler, frame_id: str, source: str = "000000"):
    dataset = KittiDataset(KITTI_SAMPLE)
    frame = dataset.load_frame(source, with_labels=False)
    result = labeler.label(frame.image, frame.points, frame.calib)
    png = dataset.image_path(source).read_bytes()
    return store.put(frame_id, png, frame.points, frame.calib, result)


def test_put_is_idempotent_and_indexed_in_wal_mode(tmp_path, served_labeler):
    store = LabelStore(tmp_path, "a")
    record, new = _put(store, served_labeler, "f1")
    again, new_again = _put(store, served_labeler, "f1", source="000001")
    assert new and not new_again and again == record
    assert store.get("f1") == record and store.get("f2") is None
    store.close()
    db = sqlite3.connect(tmp_path / "shards" / "a" / "index.sqlite")
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert db.execute("SELECT COUNT(*) FROM frames").fetchone()[0] == 1
    db.close()
    assert check_integrity(tmp_path) == []


@pytest.mark.parametrize("frame_id", ["../x", "a/b", "..", "/etc/passwd", "a" * 65, "x\0y", ""])
def test_frame_ids_cannot_escape_the_store(tmp_path, served_labeler, frame_id):
    store = LabelStore(tmp_path / "store", "a")
    with pytest.raises(ValueError, match="invalid frame id"):
        _put(store, served_labeler, frame_id)
    store.close()
    assert not any(p.is_file() for p in tmp_path.rglob("*") if p.suffix != ".sqlite" and
                   "-wal" not in p.name and "-shm" not in p.name)  # fmt: skip
    with pytest.raises(ValueError, match="invalid shard"):
        LabelStore(tmp_path / "store", "../other")


def test_shards_are_listed_and_exported_together(tmp_path, served_labeler, capsys):
    first, second = LabelStore(tmp_path / "store", "a"), LabelStore(tmp_path / "store", "b")
    _put(first, served_labeler, "f1")
    _put(second, served_labeler, "f2", source="000001")
    _put(second, served_labeler, "f1", source="000000")  # the same id on two replicas
    first.close()
    second.close()
    records = list_frames(tmp_path / "store")
    assert [r.frame_id for r in records] == ["f1", "f2"]
    assert main(["store", "export", "--store", str(tmp_path / "store"),
                 "--out", str(tmp_path / "out")]) == 0  # fmt: skip
    assert "exported 2 stored frames" in capsys.readouterr().out
    out = tmp_path / "out"
    assert read_image_set(out / "ImageSets" / "train.txt") == ["f1", "f2"]
    exported = KittiDataset(out).load_frame("f2", with_labels=False)
    source = KittiDataset(KITTI_SAMPLE).load_frame("000001", with_labels=False)
    np.testing.assert_array_equal(exported.points, source.points)
    np.testing.assert_allclose(exported.calib.P2, source.calib.P2)
    objects = read_objects(out / "training" / "label_2" / "f2.txt")
    assert objects.score is not None or len(objects) == 0
    assert (out / "labels" / "f2.json").is_file()


def test_the_store_survives_a_killed_server(tmp_path, exported_repository):
    """SIGKILL while labeling; every acknowledged frame is present and intact afterwards."""
    store = tmp_path / "store"
    acknowledged: list[str] = []
    stop = threading.Event()

    def send(target: str, worker: int) -> None:
        with LabelingClient(target, timeout_s=30) as client:
            for i in range(1000):
                if stop.is_set():
                    return
                frame_id = f"w{worker}_{i:04d}"
                try:
                    client.label_kitti_frame(KITTI_SAMPLE, "000000", send_as=frame_id)
                except grpc.RpcError:
                    return
                acknowledged.append(frame_id)

    with serve_process(exported_repository, store) as (process, target):
        threads = [threading.Thread(target=send, args=(target, w)) for w in range(3)]
        for thread in threads:
            thread.start()
        deadline = time.monotonic() + 120
        while len(acknowledged) < 6 and time.monotonic() < deadline:
            time.sleep(0.01)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
        stop.set()
        for thread in threads:
            thread.join(timeout=60)
    assert len(acknowledged) >= 6
    assert check_integrity(store) == []
    stored = {r.frame_id for r in list_frames(store)}
    assert set(acknowledged) <= stored
    with serve_process(exported_repository, store) as (process, target):
        with LabelingClient(target) as client:
            response = client.label_kitti_frame(KITTI_SAMPLE, "000000", send_as=acknowledged[0])
            assert response.stored
            client.label_kitti_frame(KITTI_SAMPLE, "000001", send_as="after_restart")
    assert {r.frame_id for r in list_frames(store)} == stored | {"after_restart"}
    assert check_integrity(store) == []
