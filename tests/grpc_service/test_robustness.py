"""Hostile and broken clients against a real server: stalled streams, a reflection stream with
one worker, bytes that are not a request, decompression bombs, huge ids, degenerate
calibrations, a busy port, and binding beyond loopback (the limits: test_limits.py)."""

from __future__ import annotations

import io
import logging
import socket

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc
from PIL import Image

from benchmarks.service_stall import IdleConnection, StalledStream
from serving.client import LabelingClient, kitti_frame, pb2, pb2_grpc
from serving.config import ServerConfig
from serving.messages import request_message
from serving.server import format_address
from serving.service import LabelingService, ModelSlot
from serving.store import LabelStore, list_frames
from serving.testing import BackgroundServer
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import running_server, serve_process


@pytest.fixture
def slot(served_labeler) -> ModelSlot:
    slot = ModelSlot()
    slot.swap(served_labeler)
    return slot


def _grpc_loop_noise(record: logging.LogRecord) -> bool:
    """asyncio's report of grpc.aio's poller still waking a closed event loop (one that an
    earlier server in this process ran on): grpc's own teardown, not this server's doing."""
    return record.name == "asyncio" and "PollerCompletionQueue" in record.getMessage()


def _health(target: str) -> int:
    with grpc.insecure_channel(target) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        return stub.Check(health_pb2.HealthCheckRequest(), timeout=5).status


def test_stalled_streams_starve_neither_health_nor_other_clients(tmp_path, slot):
    """Defect 2: as many stalled streams as --workers froze the sync server, health included.
    Here 4 x workers stalled streams and idle connections are open; health answers and a
    normal client labels; a stalled stream is dropped once the receive timeout passes."""
    config = ServerConfig(workers=1, receive_timeout_s=3.0)
    with running_server(slot, tmp_path / "store", config) as running:
        stalled = [StalledStream(running.target) for _ in range(4)]
        idle = [IdleConnection(running.target) for _ in range(4)]
        try:
            assert _health(running.target) == health_pb2.HealthCheckResponse.SERVING
            with LabelingClient(running.target, timeout_s=10) as client:
                assert client.label_kitti_frame(KITTI_SAMPLE, "000000").stored
                assert client.model_info().version == slot.version
            assert [s.status(timeout_s=30) for s in stalled] == ["4"] * 4  # DEADLINE_EXCEEDED
        finally:
            for connection in stalled + idle:
                connection.close()
    assert [r.frame_id for r in list_frames(tmp_path / "store")] == ["000000"]


def test_an_open_reflection_stream_blocks_nothing_with_one_worker(tmp_path, slot):
    """With --workers 1, grpcurl's own reflection stream used to hang every other call."""
    config = ServerConfig(workers=1)
    with running_server(slot, tmp_path / "store", config) as running:
        with grpc.insecure_channel(running.target) as channel:
            stub = reflection_pb2_grpc.ServerReflectionStub(channel)
            request = reflection_pb2.ServerReflectionRequest(list_services="")
            pending = threading_queue_iterator(request)
            responses = stub.ServerReflectionInfo(pending.iterate(), timeout=60)
            first = next(responses)
            assert first.list_services_response.service
            assert _health(running.target) == health_pb2.HealthCheckResponse.SERVING
            with LabelingClient(running.target, timeout_s=10) as client:
                answer = client.label_kitti_frame(KITTI_SAMPLE, "000001")
                assert answer.frame_id == "000001" and answer.model_version == slot.version
                assert answer.store_outcome == pb2.STORE_OUTCOME_CREATED
            pending.close()
            responses.cancel()


class threading_queue_iterator:  # noqa: N801 - reads as what it is
    """A request iterator that yields `first` and then blocks until closed (a stream kept
    open by its client, as grpcurl keeps its reflection stream)."""

    def __init__(self, first) -> None:
        import threading

        self.first = first
        self.closed = threading.Event()

    def iterate(self):
        yield self.first
        self.closed.wait(60)

    def close(self) -> None:
        self.closed.set()


def test_health_watch_streams_through_the_edge(server):
    """Health.Watch (unary request, streamed answers) is served as a stream by the edge."""
    with grpc.insecure_channel(server.target) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        answers = stub.Watch(health_pb2.HealthCheckRequest(), timeout=30)
        assert next(answers).status == health_pb2.HealthCheckResponse.SERVING
        answers.cancel()


def test_bytes_that_are_no_request_are_invalid_argument_logged_once(tmp_path, slot, caplog):
    """Defect 5: undecodable bytes were INTERNAL ('Exception deserializing request!') with
    an ERROR traceback per call, for unauthenticated callers too."""
    config = ServerConfig(token="s3cret")
    garbage = [b"\xff" * 7, b"\x0a\x05ab", b"\x12\xff\xff\xff\xff\x0f", b"\x08" * 33]
    with caplog.at_level(logging.INFO):
        with running_server(slot, tmp_path / "store", config) as running:
            with grpc.insecure_channel(running.target) as channel:
                for method in ("LabelFrame", "GetModelInfo"):
                    call = channel.unary_unary(f"/detmatch.v1.AutoLabeler/{method}")
                    for data in garbage:
                        with pytest.raises(grpc.RpcError) as caught:
                            call(data, timeout=10, metadata=(("authorization", "Bearer s3cret"),))
                        assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT, data
                        assert "not a valid request message" in caught.value.details()
                        with pytest.raises(grpc.RpcError) as stranger:
                            call(data, timeout=10)
                        assert stranger.value.code() == grpc.StatusCode.UNAUTHENTICATED
                health = channel.unary_unary("/grpc.health.v1.Health/Check")
                with pytest.raises(grpc.RpcError) as caught:
                    health(b"\xff\xff", timeout=10)
                assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    ours = [r for r in caplog.records if not _grpc_loop_noise(r)]
    assert not [r for r in ours if r.levelno >= logging.ERROR]
    assert not [r for r in ours if r.exc_info]
    warnings = [r for r in caplog.records if r.getMessage().startswith("request bytes are not")]
    assert len(warnings) == 1  # rate-limited: one line every few seconds at most
    assert list_frames(tmp_path / "store") == []


def _request(**changes):
    request = request_message(kitti_frame(KITTI_SAMPLE, "000000"))
    for name, value in changes.items():
        setattr(request, name, value)
    return request


def _bomb() -> bytes:
    buffer = io.BytesIO()
    Image.new("L", (8192, 8192)).save(buffer, format="PNG")
    return buffer.getvalue()


def test_hostile_frames_are_invalid_argument_and_store_nothing(tmp_path, slot):
    """A 8192 x 8192 PNG bomb (refused before decoding), a 16 KB frame id (its error cut to
    fit a status), all-zero and 1e308 calibrations: INVALID_ARGUMENT naming the field."""
    cases = {
        "image: 8192 x 8192 pixels": _request(image=_bomb()),
        "frame_id: invalid frame id 'xxxx": _request(frame_id="x" * 16384),
        "calibration.p2: rank-deficient": _request(),
        "calibration.tr_velo_to_cam: a value of magnitude 1e+308": _request(),
    }
    cases["calibration.p2: rank-deficient"].calibration.p2[:] = [0.0] * 12
    cases["calibration.tr_velo_to_cam: a value of magnitude 1e+308"].calibration.tr_velo_to_cam[
        :
    ] = [1e308] * 12
    with running_server(slot, tmp_path / "store") as running:
        with grpc.insecure_channel(running.target) as channel:
            stub = pb2_grpc.AutoLabelerStub(channel)
            for expected, request in cases.items():
                with pytest.raises(grpc.RpcError) as caught:
                    stub.LabelFrame(request, timeout=60)
                assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT, expected
                assert caught.value.details().startswith(expected)
                assert len(caught.value.details()) < 400
            assert stub.LabelFrame(_request(), timeout=60).stored
        assert _health(running.target) == health_pb2.HealthCheckResponse.SERVING
    assert [r.frame_id for r in list_frames(tmp_path / "store")] == ["000000"]


def test_a_second_server_on_a_busy_port_fails_to_bind(tmp_path, slot):
    """Defect 10: gRPC's SO_REUSEPORT let a second server start silently on a busy port."""
    with running_server(slot, tmp_path / "store") as running:
        store = LabelStore(tmp_path / "other", "s0")
        second = BackgroundServer(
            LabelingService(slot, store), ServerConfig(address=f"127.0.0.1:{running.port}")
        )
        with pytest.raises(OSError, match=f"cannot bind 127.0.0.1:{running.port}"):
            second.start()
        store.close()
        assert _health(running.target) == health_pb2.HealthCheckResponse.SERVING


def test_serve_listens_beyond_loopback(tmp_path, exported_repository):
    """`--host ::` (every interface, IPv6 and IPv4) was formatted ':::PORT', which gRPC
    cannot parse; `--host 0.0.0.0` is what a container needs."""
    assert format_address("::", 50051) == "[::]:50051"
    assert format_address("0.0.0.0", 1) == "0.0.0.0:1"
    if not socket.has_ipv6:
        pytest.skip("no IPv6 on this host")
    with serve_process(exported_repository, tmp_path / "store", "--host", "::") as (_, target):
        port = int(target.rsplit(":", 1)[1])
        assert target.startswith("[::]:")
        assert _health(f"127.0.0.1:{port}") == health_pb2.HealthCheckResponse.SERVING
    with serve_process(exported_repository, tmp_path / "store", "--host", "0.0.0.0") as (
        _,
        target,
    ):
        try:  # an address of this host other than loopback, where it has one
            host = socket.gethostbyname(socket.gethostname())
        except OSError:
            host = "127.0.0.1"
        port = int(target.rsplit(":", 1)[1])
        assert _health(f"{host}:{port}") == health_pb2.HealthCheckResponse.SERVING


def test_the_response_says_what_the_store_did(server):
    with LabelingClient(server.target) as client:
        created = client.label_kitti_frame(KITTI_SAMPLE, "000002")
        not_stored = client.label_kitti_frame(KITTI_SAMPLE, "000001", store=False)
    assert created.store_outcome == pb2.STORE_OUTCOME_CREATED and created.namespace == "default"
    assert not_stored.store_outcome == pb2.STORE_OUTCOME_NOT_STORED and not not_stored.stored
    assert np.isfinite(created.timing.store_s) and created.timing.store_s > 0
