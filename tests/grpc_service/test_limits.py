"""The service under heavy and stalled clients (a real server on port 0): labeling slots taken
only by complete requests, a per-connection cap on uploads in progress, the byte budget for
frames in flight (queue, then refuse), the point cap, and client mistakes logged as one
rate-limited WARNING line each, never a traceback."""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor

import grpc
import pytest
from prometheus_client import generate_latest

from benchmarks.service_stall import StalledStream
from serving.client import LabelingClient, kitti_frame, pb2
from serving.config import MAX_HEADER_BYTES, ServerConfig
from serving.messages import request_message
from serving.service import ModelSlot
from serving.store import list_frames
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import prometheus_sample, running_server

TOKEN = "s3cret"
AUTH = [("authorization", f"Bearer {TOKEN}")]


class GatedLabeler:
    """The served labeler, holding each call at a gate until the test opens it: a call that
    stays in flight as long as a test needs."""

    def __init__(self, labeler) -> None:
        self._labeler = labeler
        self.entered = threading.Semaphore(0)
        self.gate = threading.Event()

    def label(self, *args, **kwargs):
        self.entered.release()
        assert self.gate.wait(60), "the test never opened the gate"
        return self._labeler.label(*args, **kwargs)

    def __getattr__(self, name: str):
        return getattr(self._labeler, name)


@pytest.fixture
def gated(served_labeler) -> tuple[ModelSlot, GatedLabeler]:
    labeler = GatedLabeler(served_labeler)
    slot = ModelSlot()
    slot.swap(labeler)
    return slot, labeler


def _client(running, **kwargs) -> LabelingClient:
    return LabelingClient(running.target, token=TOKEN, timeout_s=30, **kwargs)


def _label(running, frame_id: str = "000000", store: bool = False):
    with _client(running) as client:
        return client.label_kitti_frame(KITTI_SAMPLE, frame_id, store=store)


def _refusal(running, frame_id: str = "000000") -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as caught:
        _label(running, frame_id)
    return caught.value


def _hold_one_call(running, labeler: GatedLabeler, pool: ThreadPoolExecutor):
    """Frame 000001's call, sent on the pool and held at the labeler's gate: its future."""
    first = pool.submit(_label, running, "000001")
    assert labeler.entered.acquire(timeout=30)
    return first


def _message_bytes() -> int:
    return request_message(kitti_frame(KITTI_SAMPLE, "000000")).ByteSize()


def test_stalled_uploads_hold_no_labeling_slot(tmp_path, served_labeler):
    """70 authenticated streams that sent headers and part of a message, then stalled, on 5
    connections: with 4 labeling slots, honest LabelFrame and GetModelInfo calls answer."""
    slot = ModelSlot()
    slot.swap(served_labeler)
    config = ServerConfig(token=TOKEN, max_concurrent_rpcs=4, receive_timeout_s=120.0)
    with running_server(slot, tmp_path / "store", config) as running:
        stalled = [StalledStream(running.target, streams=14, headers=AUTH) for _ in range(5)]
        try:
            with _client(running) as client:
                for frame_id in ("000000", "000001", "000002", "000000", "000001"):
                    assert client.label_kitti_frame(KITTI_SAMPLE, frame_id).labels is not None
                    assert client.model_info().version == slot.version
            assert all(s.statuses(0.2) == dict.fromkeys(s.stream_ids) for s in stalled)
        finally:
            for stream in stalled:
                stream.close()


def test_one_connection_gets_no_more_uploads_than_its_cap(tmp_path, served_labeler):
    slot = ModelSlot()
    slot.swap(served_labeler)
    config = ServerConfig(token=TOKEN, max_uploads_per_peer=3, receive_timeout_s=120.0)
    with running_server(slot, tmp_path / "store", config) as running:
        stalled = StalledStream(running.target, streams=5, headers=AUTH)
        try:
            endings = stalled.statuses(timeout_s=10)
            assert sorted(endings.values(), key=str) == ["8", "8", None, None, None]
            assert _label(running).frame_id == "000000"  # another connection: its own cap
        finally:
            stalled.close()


def test_calls_beyond_the_slots_are_refused_while_model_info_answers(tmp_path, gated):
    slot, labeler = gated
    config = ServerConfig(token=TOKEN, max_concurrent_rpcs=1, workers=2)
    with running_server(slot, tmp_path / "store", config) as running:
        with ThreadPoolExecutor(1) as pool:
            first = _hold_one_call(running, labeler, pool)
            refused = _refusal(running)
            assert refused.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "1 labeling calls in flight, the limit is 1" in refused.details()
            with _client(running) as client:
                assert client.model_info().version == slot.version
            labeler.gate.set()
            assert first.result(timeout=60).frame_id == "000001"
        assert _label(running).frame_id == "000000"


def test_the_byte_budget_queues_then_refuses_and_frees_its_bytes(tmp_path, gated):
    """A KITTI frame's message is S bytes and holds 3 S in flight; with a budget of 4 S one
    call fits at a time: the next waits for it (served when it ends in time, refused naming
    the budget when not), and a frame bigger than the whole budget is refused at once."""
    slot, labeler = gated
    size = _message_bytes()
    config = ServerConfig(token=TOKEN, workers=2, max_inflight_bytes=4 * size, budget_wait_s=1.0)
    with running_server(slot, tmp_path / "store", config) as running:
        with ThreadPoolExecutor(2) as pool:
            first = _hold_one_call(running, labeler, pool)
            refused = _refusal(running)
            assert refused.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "of the 0 MB budget" not in refused.details()
            assert refused.details().startswith("server busy: frames in flight hold")
            queued = pool.submit(_label, running, "000002")
            threading.Timer(0.3, labeler.gate.set).start()
            assert first.result(timeout=60).frame_id == "000001"
            assert queued.result(timeout=60).frame_id == "000002"
        assert _label(running).frame_id == "000000"  # every byte was given back

    small = ServerConfig(token=TOKEN, max_inflight_bytes=2 * size, budget_wait_s=30.0)
    with running_server(slot, tmp_path / "store2", small) as running:
        refused = _refusal(running)
        assert refused.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "more than all of it" in refused.details()
    assert list_frames(tmp_path / "store2") == []


def test_frames_over_the_point_cap_are_invalid_argument(tmp_path, served_labeler):
    slot = ModelSlot()
    slot.swap(served_labeler)
    config = ServerConfig(token=TOKEN, max_points=1000)
    with running_server(slot, tmp_path / "store", config) as running:
        refused = _refusal(running)
    assert refused.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert refused.details().startswith("points: ")
    assert refused.details().endswith("exceeds the limit of 1000 points per frame")


def _grpc_loop_noise(record: logging.LogRecord) -> bool:
    return record.name == "asyncio" and "PollerCompletionQueue" in record.getMessage()


def test_client_mistakes_are_warnings_without_tracebacks(tmp_path, gated, caplog):
    """A call cancelled while it runs, a non-UTF-8 authorization header and an 8 KB token:
    each a WARNING line without a traceback, counted by kind; nothing at ERROR. A token is
    refused the same way on every call: by authentication under the header limit, by gRPC
    over it."""
    slot, labeler = gated
    config = ServerConfig(token=TOKEN, workers=2)
    with caplog.at_level(logging.INFO):
        with running_server(slot, tmp_path / "store", config) as running:
            with _client(running) as client:
                request = request_message(kitti_frame(KITTI_SAMPLE, "000000"))
                future = client.stub.LabelFrame.future(request, metadata=AUTH, timeout=30)
                assert labeler.entered.acquire(timeout=30)
                future.cancel()
                labeler.gate.set()
                bad = StalledStream(
                    running.target, headers=[(b"authorization", b"Bearer \xff\xfe")]
                )
                assert bad.status(timeout_s=10) in ("16", "reset", "closed")
                bad.close()
                for size, code in (
                    (8192, grpc.StatusCode.UNAUTHENTICATED),
                    (MAX_HEADER_BYTES, grpc.StatusCode.RESOURCE_EXHAUSTED),
                ):
                    for _ in range(5):  # gRPC's default limit decides at random in this range
                        with pytest.raises(grpc.RpcError) as caught:
                            client.stub.GetModelInfo(
                                pb2.GetModelInfoRequest(),
                                timeout=10,
                                metadata=[("authorization", "Bearer " + "x" * size)],
                            )
                        assert caught.value.code() == code, size
                assert client.model_info().version == slot.version
            text = generate_latest(running.background.metrics.registry).decode()
    ours = [r for r in caplog.records if not _grpc_loop_noise(r)]
    assert not [r for r in ours if r.levelno >= logging.ERROR], [r.getMessage() for r in ours]
    assert not [r for r in ours if r.exc_info]
    warnings = {r.getMessage() for r in ours if r.levelno == logging.WARNING}
    assert "unauthenticated call refused" in warnings
    assert any(w.startswith("call ended by the client") or w.startswith("call cancelled")
               for w in warnings), warnings  # fmt: skip
    assert prometheus_sample(text, "detmatch_client_errors_total", kind="unauthenticated") >= 1
    # the server sees each call gRPC refused for its headers as cancelled: 1 + 5
    assert prometheus_sample(text, "detmatch_client_errors_total", kind="cancelled") == 6
    assert prometheus_sample(text, "detmatch_client_errors_total", kind="header not UTF-8") == 1
