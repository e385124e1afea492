"""Bearer-token auth (health exempt), TLS, and the Prometheus metrics endpoint."""

from __future__ import annotations

import shutil
import subprocess
import urllib.request

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from serving.client import LabelingClient
from serving.metrics import ServiceMetrics
from serving.server import ServerConfig, create_server
from serving.service import LabelingService, ModelSlot
from serving.store import LabelStore, list_frames
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import running_server


@pytest.fixture
def slot(served_labeler) -> ModelSlot:
    slot = ModelSlot()
    slot.swap(served_labeler)
    return slot


def test_bearer_token_is_required_except_for_health(tmp_path, slot):
    config = ServerConfig(token="s3cret")
    with running_server(slot, tmp_path / "store", config) as running:
        for token in (None, "wrong"):
            with LabelingClient(running.target, token=token) as client:
                for call in (client.model_info, lambda c=client: c.label_kitti_frame(
                        KITTI_SAMPLE, "000000")):  # fmt: skip
                    with pytest.raises(grpc.RpcError) as caught:
                        call()
                    assert caught.value.code() == grpc.StatusCode.UNAUTHENTICATED
        assert list_frames(running.store_root) == []
        with grpc.insecure_channel(running.target) as channel:
            stub = reflection_pb2_grpc.ServerReflectionStub(channel)
            request = reflection_pb2.ServerReflectionRequest(list_services="")
            with pytest.raises(grpc.RpcError) as caught:
                list(stub.ServerReflectionInfo(iter([request]), timeout=10))
            assert caught.value.code() == grpc.StatusCode.UNAUTHENTICATED
        with grpc.insecure_channel(running.target) as channel:
            status = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(), timeout=10
            )
            assert status.status == health_pb2.HealthCheckResponse.SERVING
        with LabelingClient(running.target, token="s3cret") as client:
            assert client.label_kitti_frame(KITTI_SAMPLE, "000000").stored


@pytest.fixture
def certificate(tmp_path):
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is needed to make a test certificate")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
         "-keyout", str(key), "-out", str(cert), "-subj", "/CN=localhost",
         "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
        check=True, capture_output=True,
    )  # fmt: skip
    return cert, key


def test_tls(tmp_path, slot, certificate):
    cert, key = certificate
    config = ServerConfig(tls_cert=cert, tls_key=key, token="t")
    with running_server(slot, tmp_path / "store", config) as running:
        target = f"localhost:{running.port}"
        with LabelingClient(target, token="t", root_certificates=cert.read_bytes()) as client:
            assert client.label_kitti_frame(KITTI_SAMPLE, "000000").stored
        with LabelingClient(target, token="t", timeout_s=5) as plaintext:
            with pytest.raises(grpc.RpcError) as caught:
                plaintext.model_info()
            assert caught.value.code() == grpc.StatusCode.UNAVAILABLE


def test_tls_needs_both_files(tmp_path, slot, certificate):
    store = LabelStore(tmp_path / "store", "s0")
    with pytest.raises(ValueError, match="both a certificate and a key"):
        create_server(LabelingService(slot, store), ServerConfig(tls_cert=certificate[0]))
    store.close()


def test_metrics_endpoint(tmp_path, slot):
    store = LabelStore(tmp_path / "store", "s0")
    metrics = ServiceMetrics()
    server, port, _ = create_server(LabelingService(slot, store), ServerConfig(), metrics)
    slot.swap(slot.labeler)  # announce the served version to the new server's listeners
    server.start()
    try:
        metrics_port = metrics.serve(0)
        with LabelingClient(f"127.0.0.1:{port}") as client:
            response = client.label_kitti_frame(KITTI_SAMPLE, "000000")
            with pytest.raises(grpc.RpcError):
                client.label_frame("../x", b"", b"", store=False, calib=_calib())
        url = f"http://127.0.0.1:{metrics_port}/metrics"
        text = urllib.request.urlopen(url, timeout=10).read().decode()
    finally:
        server.stop(None).wait()
        store.close()
    assert 'detmatch_requests_total{code="OK",method="LabelFrame"} 1.0' in text
    assert 'detmatch_errors_total{code="INVALID_ARGUMENT",method="LabelFrame"} 1.0' in text
    assert 'detmatch_request_seconds_count{method="LabelFrame"} 2.0' in text
    assert f"detmatch_labels_total {float(len(response.labels))}" in text
    assert f'detmatch_model_info{{version="{slot.version}"}} 1.0' in text


def _calib():
    from detmatch.data.kitti import read_calib

    return read_calib(KITTI_SAMPLE / "training" / "calib" / "000000.txt")
