"""Graceful shutdown: health goes NOT_SERVING, calls in flight finish; SIGTERM does it."""

from __future__ import annotations

import json
import signal
import threading
import time
import urllib.request

import grpc
from grpc_health.v1 import health_pb2

from serving.client import LabelingClient, kitti_frame, pb2
from serving.config import ServerConfig
from serving.messages import request_message
from serving.service import LabelingService, ModelSlot
from serving.store import LabelStore, check_integrity, list_frames
from serving.testing import BackgroundServer
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import prometheus_sample, serve_process


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
        future = client.stub.LabelFrame.future(_request(), timeout=60)
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


def _request():
    return request_message(kitti_frame(KITTI_SAMPLE, "000000"))


def _labeling_calls_in_flight(metrics_port: int) -> float:
    url = f"http://127.0.0.1:{metrics_port}/metrics"
    text = urllib.request.urlopen(url, timeout=10).read().decode()
    return prometheus_sample(text, "detmatch_requests_in_flight", method="LabelFrame")


def test_sigterm_drains_and_exits_cleanly(tmp_path, exported_repository):
    """`detmatch serve` in a process that cannot import torch: serves, then drains on SIGTERM.
    SIGTERM is sent once a LabelFrame call is in the server (the metrics' in-flight gauge),
    so at least one call must finish OK during the drain; the others finish OK or are
    refused (UNAVAILABLE); the frame is stored because a call for it was answered OK."""
    store = tmp_path / "store"
    args = ("--grace-s", "30", "--metrics-port", "0")
    with serve_process(exported_repository, store, *args) as (process, target):
        line = ""
        while '"metrics endpoint"' not in line:
            line = process.stderr.readline()
            assert line, "no metrics endpoint line in the log"
        metrics_port = int(json.loads(line)["address"].rsplit(":", 1)[1])
        with LabelingClient(target) as client:
            first = client.label_kitti_frame(KITTI_SAMPLE, "000001")
            futures = [client.stub.LabelFrame.future(_request(), timeout=60) for _ in range(4)]
            deadline = time.monotonic() + 30
            while _labeling_calls_in_flight(metrics_port) < 1 and not all(
                f.done() for f in futures
            ):
                assert time.monotonic() < deadline, "no LabelFrame call reached the server"
                time.sleep(0.005)
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
    assert first.model_version == "000001"
    assert first.store_outcome == pb2.STORE_OUTCOME_CREATED
    assert grpc.StatusCode.OK in codes, codes
    assert set(codes) <= {grpc.StatusCode.OK, grpc.StatusCode.UNAVAILABLE}, codes
    assert '"message": "draining"' in log and '"message": "stopped"' in log
    stored = {r.frame_id for r in list_frames(store)}
    assert "000001" in stored
    assert ("000000" in stored) == (grpc.StatusCode.OK in codes)
    assert check_integrity(store) == []
