"""The label store behind the gRPC server: a re-label after a model swap, namespaces over the
wire, and a server killed while storing (the store itself: tests/serving/test_store.py)."""

from __future__ import annotations

import signal
import threading
import time

import grpc
import pytest

from detmatch.data.kitti import KittiDataset
from serving.client import LabelingClient, kitti_frame
from serving.messages import request_message
from serving.store import (
    check_integrity,
    list_frames,
)
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import send_frames, serve_process
from tests.serving.store_helpers import (
    listed_files,
    shard_files,
)


def test_a_relabel_over_grpc_after_a_model_swap_replaces_the_stored_labels(
    server, served_labeler, exported_repository, tmp_path
):
    from serving.labeler import Labeler
    from tests.grpc_service.conftest import add_version, copy_repository

    repository = copy_repository(exported_repository, tmp_path / "models")
    add_version(repository, "000002")
    with LabelingClient(server.target) as client:
        first = client.label_kitti_frame(KITTI_SAMPLE, "000000")
        retry = client.label_kitti_frame(KITTI_SAMPLE, "000000")
        server.service.slot.swap(Labeler.from_repository(repository, 2))
        relabel = client.label_kitti_frame(KITTI_SAMPLE, "000000")
    from serving.client import pb2

    assert first.store_outcome == pb2.STORE_OUTCOME_CREATED and first.stored
    assert retry.store_outcome == pb2.STORE_OUTCOME_UNCHANGED
    assert retry.previous_model_version == "000001"
    assert relabel.store_outcome == pb2.STORE_OUTCOME_REPLACED
    assert (relabel.model_version, relabel.previous_model_version) == ("000002", "000001")
    (record,) = list_frames(server.store_root)
    assert record.model_version == "000002" == relabel.model_version


def test_namespaces_keep_equal_frame_ids_apart(server):
    """KITTI's training/000000 and testing/000000 (or two sites' frames) no longer collide."""
    with LabelingClient(server.target) as client:
        request = request_message(kitti_frame(KITTI_SAMPLE, "000000"))
        training = client.stub.LabelFrame(request, timeout=60)
        request.namespace = "kitti-testing"
        request.points = KittiDataset(KITTI_SAMPLE).load_frame("000001").points.tobytes()
        testing = client.stub.LabelFrame(request, timeout=60)
        with pytest.raises(grpc.RpcError) as caught:
            request.namespace = "../up"
            client.stub.LabelFrame(request, timeout=60)
    assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "namespace: invalid namespace" in caught.value.details()
    assert (training.namespace, testing.namespace) == ("default", "kitti-testing")
    assert training.store_outcome == testing.store_outcome == 1  # both CREATED
    records = list_frames(server.store_root)
    assert [(r.namespace, r.frame_id) for r in records] == [
        ("default", "000000"),
        ("kitti-testing", "000000"),
    ]
    assert records[0].files != records[1].files
    assert check_integrity(server.store_root) == []


def test_the_store_survives_a_killed_server(tmp_path, exported_repository):
    """SIGKILL while labeling; every acknowledged frame is present and intact afterwards, and
    the restart leaves no debris: every file is one an index row lists."""
    store = tmp_path / "store"
    acknowledged: list[str] = []
    stop = threading.Event()

    with serve_process(exported_repository, store) as (process, target):
        threads = [
            threading.Thread(target=send_frames, args=(target, f"w{w}", acknowledged, stop))
            for w in range(3)
        ]
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
            assert response.stored and response.store_outcome == 2  # UNCHANGED
            client.label_kitti_frame(KITTI_SAMPLE, "000001", send_as="after_restart")
    assert {r.frame_id for r in list_frames(store)} == stored | {"after_restart"}
    assert check_integrity(store) == []
    assert shard_files(store) == listed_files(store)
