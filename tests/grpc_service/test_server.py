"""A real server on 127.0.0.1 port 0: round trips, model info, health, reflection, and every
class of invalid input (INVALID_ARGUMENT naming the field; the server stays healthy)."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc
from PIL import Image

from detmatch.data.kitti import KittiDataset
from serving.client import LabelingClient, kitti_frame, pb2
from serving.config import ServerConfig
from serving.messages import request_message
from serving.request import FrameRequest, LabelOptions
from serving.service import ModelSlot
from serving.servicer import SERVICE_NAME
from serving.store import check_integrity, list_frames
from tests.conftest import KITTI_SAMPLE, REPO
from tests.grpc_service.conftest import running_server


def check_health(target: str, service: str = "") -> int:
    with grpc.insecure_channel(target) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        return stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=10).status


# The test model trains for a few steps: none of its scores reach the manifest's thresholds.
# With these overrides it labels (about 20 matched labels a frame), so the round trip compares
# every field of real labels, and the overrides themselves cross the wire.
LABEL_EVERYTHING = LabelOptions(score_threshold_2d=0.01, score_threshold_3d=0.01, tau_hung=10.0)


@pytest.mark.parametrize("source", ["synthetic", "kitti", "kitti raw pixels"])
def test_round_trip_matches_the_labeler_and_is_stored(server, served_labeler, synth_root, source):
    root = synth_root if source == "synthetic" else KITTI_SAMPLE
    frame_id = KittiDataset(root).ids()[0] if source == "synthetic" else "000001"
    frame = KittiDataset(root).load_frame(frame_id, with_labels=False)
    expected = served_labeler.label(
        frame.image, frame.points, frame.calib, score_threshold_2d=0.01, score_threshold_3d=0.01,
        tau_hung=10.0,
    )  # fmt: skip
    with LabelingClient(server.target) as client:
        request = kitti_frame(root, frame_id, options=LABEL_EVERYTHING,
                              raw_image=source.endswith("raw pixels"))  # fmt: skip
        assert (request.raw_image is not None) == source.endswith("raw pixels")
        response = client.label_frame(request)
    assert response.frame_id == frame_id
    assert response.model_version == served_labeler.version
    assert response.stored
    assert len(response.labels) == len(expected) > 0
    for label, i in zip(response.labels, range(len(expected)), strict=True):
        box = [label.box_3d.x, label.box_3d.y, label.box_3d.z, label.box_3d.l,
               label.box_3d.w, label.box_3d.h, label.box_3d.yaw]  # fmt: skip
        np.testing.assert_allclose(box, expected.labels.boxes_3d[i], rtol=1e-6, atol=1e-6)
        assert label.class_name == expected.names[i]
        assert label.provenance == int(expected.labels.provenance[i])
        if label.provenance == pb2.PROVENANCE_MATCHED:
            assert label.HasField("box_2d") and label.HasField("match_cost")
            assert label.match_cost == pytest.approx(expected.labels.cost[i])
        else:
            assert not label.HasField("box_2d") and not label.HasField("score_2d")
    assert response.timing.total_s > 0
    records = list_frames(server.store_root)
    assert [r.frame_id for r in records] == [frame_id]
    assert records[0].num_labels == len(expected)
    stored = KittiDataset(
        server.store_root / "shards" / "s0" / "namespaces" / "default"
    ).load_frame(frame_id)
    np.testing.assert_array_equal(stored.points, frame.points)
    np.testing.assert_array_equal(stored.image, frame.image)
    assert check_integrity(server.store_root) == []


def test_model_info_health_and_reflection(server, served_labeler):
    with LabelingClient(server.target) as client:
        info = client.model_info()
    assert info.version == served_labeler.version
    assert list(info.classes) == list(served_labeler.classes)
    assert info.tau_hung == pytest.approx(served_labeler.tau_hung)
    assert "3d" in info.metrics_json
    assert check_health(server.target) == health_pb2.HealthCheckResponse.SERVING
    assert check_health(server.target, SERVICE_NAME) == health_pb2.HealthCheckResponse.SERVING
    with grpc.insecure_channel(server.target) as channel:
        stub = reflection_pb2_grpc.ServerReflectionStub(channel)
        request = reflection_pb2.ServerReflectionRequest(list_services="")
        (answer,) = list(stub.ServerReflectionInfo(iter([request]), timeout=10))
        names = {s.name for s in answer.list_services_response.service}
    assert {SERVICE_NAME, "grpc.health.v1.Health"} <= names


def test_not_serving_and_unavailable_until_a_model_is_loaded(tmp_path, served_labeler):
    slot = ModelSlot()
    with running_server(slot, tmp_path / "store") as running:
        assert check_health(running.target) == health_pb2.HealthCheckResponse.NOT_SERVING
        with LabelingClient(running.target) as client:
            with pytest.raises(grpc.RpcError) as caught:
                client.model_info()
            assert caught.value.code() == grpc.StatusCode.UNAVAILABLE
            slot.swap(served_labeler)
            assert check_health(running.target) == health_pb2.HealthCheckResponse.SERVING
            assert client.model_info().version == served_labeler.version


def _png(width: int = 64, height: int = 32) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), (90, 90, 90)).save(buffer, format="PNG")
    return buffer.getvalue()


def _valid_request() -> pb2.LabelFrameRequest:
    frame = KittiDataset(KITTI_SAMPLE).load_frame("000000", with_labels=False)
    points = np.zeros((10, 4), "<f4")
    return request_message(FrameRequest.from_arrays("frame_0", _png(), points, frame.calib))


def _raw(width: int, height: int, size: int | None = None):
    def change(request) -> None:
        request.image = b""
        request.raw_image.width, request.raw_image.height = width, height
        request.raw_image.rgb = b"\x5a" * (width * height * 3 if size is None else size)

    return change


def _both_images(request) -> None:
    _raw(64, 32)(request)
    request.image = _png()


def _nan_points() -> bytes:
    points = np.zeros((5, 4), "<f4")
    points[3, 1] = np.nan
    return points.tobytes()


INVALID = {
    "frame id with a slash": (lambda r: setattr(r, "frame_id", "a/b"), "frame_id"),
    "empty frame id": (lambda r: setattr(r, "frame_id", ""), "frame_id"),
    "traversal frame id": (lambda r: setattr(r, "frame_id", "../../etc"), "frame_id"),
    "empty image": (lambda r: setattr(r, "image", b""), "image: empty"),
    "not an image": (lambda r: setattr(r, "image", b"GIF89a" + b"0" * 50), "not PNG or JPEG"),
    "truncated PNG": (lambda r: setattr(r, "image", _png()[:40]), "cannot decode PNG"),
    "raw pixels and a PNG": (_both_images, "image: set image (PNG or JPEG) or raw_image, not both"),
    "raw pixels short": (_raw(64, 32, 64 * 32 * 3 - 1), "raw_image: rgb holds 6143 bytes"),
    "raw pixels zero wide": (_raw(0, 32, 0), "raw_image: 0 x 32 pixels"),
    "raw pixels too many": (_raw(5000, 5000, 30), "exceeds the limit of 8294400 pixels"),
    "empty cloud": (lambda r: setattr(r, "points", b""), "points: empty"),
    "wrong byte length": (lambda r: setattr(r, "points", b"\0" * 20), "multiple of 16"),
    "NaN point": (lambda r: setattr(r, "points", _nan_points()), "NaN or Inf (first at row 3)"),
    "short P2": (lambda r: r.calibration.p2.pop(), "calibration.p2: expected 12 values, got 11"),
    "long R0": (lambda r: r.calibration.r0_rect.append(1.0), "calibration.r0_rect: expected 9"),
    "missing Tr": (lambda r: r.calibration.ClearField("tr_velo_to_cam"), "tr_velo_to_cam"),
    "Inf in P2": (lambda r: r.calibration.p2.__setitem__(0, float("inf")), "NaN or Inf"),
    "bad threshold": (
        lambda r: setattr(r.options, "score_threshold_3d", 1.5),
        "score_threshold_3d",
    ),
    "NaN tau_hung": (lambda r: setattr(r.options, "tau_hung", float("nan")), "tau_hung"),
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_input_is_invalid_argument_naming_the_field(server, case):
    change, expected = INVALID[case]
    request = _valid_request()
    change(request)
    with grpc.insecure_channel(server.target) as channel:
        stub = pb2_grpc_stub(channel)
        with pytest.raises(grpc.RpcError) as caught:
            stub.LabelFrame(request, timeout=30)
        assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert expected in caught.value.details()
        assert stub.LabelFrame(_valid_request(), timeout=30).frame_id == "frame_0"
    assert check_health(server.target) == health_pb2.HealthCheckResponse.SERVING
    assert [r.frame_id for r in list_frames(server.store_root)] == ["frame_0"]


def pb2_grpc_stub(channel):
    from serving.client import pb2_grpc

    return pb2_grpc.AutoLabelerStub(channel)


def test_oversize_request_is_resource_exhausted(tmp_path, served_labeler):
    slot = ModelSlot()
    slot.swap(served_labeler)
    config = ServerConfig(max_message_bytes=1024 * 1024)
    with running_server(slot, tmp_path / "store", config) as running:
        request = _valid_request()
        request.points = np.zeros((100_000, 4), "<f4").tobytes()  # 1.6 MB
        with LabelingClient(running.target) as client:
            with pytest.raises(grpc.RpcError) as caught:
                client.stub.LabelFrame(request, timeout=30)
            assert caught.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            answer = client.stub.LabelFrame(_valid_request(), timeout=30)
            assert answer.frame_id == "frame_0" and answer.stored
        assert check_health(running.target) == health_pb2.HealthCheckResponse.SERVING


def test_default_message_limit_fits_a_full_kitti_frame_many_times():
    frame_bytes = 120_000 * 16 + 1242 * 375 * 3  # points + an uncompressed-size image
    assert ServerConfig().max_message_bytes >= 10 * frame_bytes


def test_retries_are_idempotent(server):
    with LabelingClient(server.target) as client:
        first = client.label_kitti_frame(KITTI_SAMPLE, "000002")
        before = list_frames(server.store_root)
        second = client.label_kitti_frame(KITTI_SAMPLE, "000002")
    assert len(second.labels) == len(first.labels)
    assert list_frames(server.store_root) == before
    assert len(before) == 1


def test_store_false_does_not_store(server):
    with LabelingClient(server.target) as client:
        response = client.label_kitti_frame(KITTI_SAMPLE, "000000", store=False)
    assert not response.stored
    assert list_frames(server.store_root) == []


def test_expired_deadline_is_deadline_exceeded(server):
    with LabelingClient(server.target) as client:
        with pytest.raises(grpc.RpcError) as caught:
            client.label_kitti_frame(KITTI_SAMPLE, "000000", timeout_s=1e-4)
    assert caught.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    assert check_health(server.target) == health_pb2.HealthCheckResponse.SERVING


def test_jpeg_frames_are_labeled_and_stored_as_png(server):
    frame = KittiDataset(KITTI_SAMPLE).load_frame("000000", with_labels=False)
    buffer = io.BytesIO()
    Image.fromarray(frame.image).save(buffer, format="JPEG", quality=90)
    with LabelingClient(server.target) as client:
        request = FrameRequest.from_arrays("jpeg_0", buffer.getvalue(), frame.points, frame.calib)
        response = client.label_frame(request)
    assert response.stored
    stored = KittiDataset(
        server.store_root / "shards" / "s0" / "namespaces" / "default"
    ).load_frame("jpeg_0")
    decoded = np.asarray(Image.open(io.BytesIO(buffer.getvalue())).convert("RGB"))
    np.testing.assert_array_equal(stored.image, decoded)


def test_example_script_prints_the_labels(server):
    command = [sys.executable, str(REPO / "examples" / "label_frame.py"), "--target",
               server.target, "--data", str(KITTI_SAMPLE), "--frame", "000002"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("frame default/000002: ")
    assert "model version 000001" in done.stdout and "(stored: created)" in done.stdout
