"""The fast part of benchmarks/service_fuzz.py: every kind of malformed LabelFrame request and
raw bytes at the method against a real in-process server with its store on. No call may end
INTERNAL or UNKNOWN, the server must stay SERVING and keep labeling, and only the calls that
succeeded may change the store."""

from __future__ import annotations

import logging
from collections import Counter

import grpc
from grpc_health.v1 import health_pb2

from benchmarks.service_common import sample_requests
from benchmarks.service_fuzz import fuzz_cases, run_cases
from serving.client import LabelingClient
from serving.store import check_integrity, list_frames
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.test_server import check_health


def test_malformed_requests_are_never_internal(server, caplog):
    cases = fuzz_cases(sample_requests(prefix="valid"), 160, seed=1, large=False)
    assert len({c.kind for c in cases}) >= 80  # every fixed kind, then random variations
    codes: Counter[str] = Counter()
    accepted = set()
    with caplog.at_level(logging.WARNING):
        for case, code, details in run_cases(server.target, cases):
            codes[code.name] += 1
            assert code not in (grpc.StatusCode.INTERNAL, grpc.StatusCode.UNKNOWN), (
                case.kind,
                details,
            )
            if code == grpc.StatusCode.INVALID_ARGUMENT:
                assert details and len(details) < 1000, case.kind
            if code == grpc.StatusCode.OK:
                accepted.add((case.request.namespace or "default", case.request.frame_id))
    assert codes["INVALID_ARGUMENT"] > 100
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert check_health(server.target) == health_pb2.HealthCheckResponse.SERVING
    with LabelingClient(server.target) as client:
        assert client.label_kitti_frame(KITTI_SAMPLE, "000000", send_as="after").stored
    stored = {r.key for r in list_frames(server.store_root)}
    assert stored == accepted | {("default", "after")}
    assert check_integrity(server.store_root) == []
