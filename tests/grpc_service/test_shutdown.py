"""Graceful shutdown: health goes NOT_SERVING, calls in flight finish; SIGTERM does it."""

from __future__ import annotations

import signal
import threading
import time

import grpc
from grpc_health.v1 import health_pb2

from serving.client import LabelingClient
from serving.server import BackgroundServer, ServerConfig
from serving.service import LabelingService, ModelSlot
from serving.store import LabelStore, check_integrity, list_frames
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import serve_process


class BlockingLabeler:
    """The served labeler, held inside label() until released."""

    def __init__(self, labeler) -> None:
        self.labeler = labeler
        self.version = labeler.version
        self.entered = threading.Event()
        self.release = threading.Event()

    def label(self, *args, **kwargs):
        self.entered.set()
        assert self.release.wait(60)
        return self.labeler.label(*args, **kwargs)


def test_shutdown_drains_calls_in_flight(tmp_path, served_labeler):
    blocking = BlockingLabeler(served_labeler)
    slot = ModelSlot()
    slot.swap(blocking)
    store = LabelStore(tmp_path / "store", "s0")
    background = BackgroundServer(LabelingService(slot, store), ServerConfig())
    port = background.start()
    health = background.server.health
    with LabelingClient(f"127.0.0.1:{port}") as client:
        future = client.stub.LabelFrame.future(_request(client), timeout=60)
        assert blocking.entered.wait(30)
        stopper = threading.Thread(target=background.stop, args=(30.0,))
        stopper.start()
        request = health_pb2.HealthCheckRequest()
        deadline = time.monotonic() + 10
        while (
            background.call(health.Check(request, None)).status
            != health_pb2.HealthCheckResponse.NOT_SERVING
        ):
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert stopper.is_alive()  # waiting for the call in flight
        blocking.release.set()
        assert future.result().model_version == served_labeler.version
        stopper.join(timeout=30)
        assert not stopper.is_alive()
    assert [r.frame_id for r in list_frames(tmp_path / "store")] == ["000000"]
    store.close()


def _request(client: LabelingClient):
    from detmatch.data.kitti import KittiDataset
    from serving.client import calibration_message, pb2
    from serving.decode import encode_points

    dataset = KittiDataset(KITTI_SAMPLE)
    frame = dataset.load_frame("000000", with_labels=False)
    return pb2.LabelFrameRequest(
        frame_id="000000",
        image=dataset.image_path("000000").read_bytes(),
        points=encode_points(frame.points),
        calibration=calibration_message(frame.calib),
    )


def test_sigterm_drains_and_exits_cleanly(tmp_path, exported_repository):
    """`detmatch serve` in a process that cannot import torch: serves, then drains on SIGTERM."""
    store = tmp_path / "store"
    with serve_process(exported_repository, store, "--grace-s", "30") as (process, target):
        with LabelingClient(target) as client:
            first = client.label_kitti_frame(KITTI_SAMPLE, "000001")
            futures = [
                client.stub.LabelFrame.future(_request(client), timeout=60) for _ in range(4)
            ]
            time.sleep(0.05)
            process.send_signal(signal.SIGTERM)
            codes = []
            for future in futures:
                try:
                    future.result()
                    codes.append(grpc.StatusCode.OK)
                except grpc.RpcError as error:
                    codes.append(error.code())
        assert process.wait(timeout=60) == 0
        log = process.stderr.read()
    assert first.labels is not None
    assert set(codes) <= {grpc.StatusCode.OK, grpc.StatusCode.UNAVAILABLE}
    assert '"message": "draining"' in log and '"message": "stopped"' in log
    stored = {r.frame_id for r in list_frames(store)}
    assert "000001" in stored
    assert ("000000" in stored) == (grpc.StatusCode.OK in codes)
    assert check_integrity(store) == []
