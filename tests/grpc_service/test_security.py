"""Bearer-token auth (health exempt), TLS, and the Prometheus metrics endpoint."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import urllib.request

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from serving.client import LabelingClient, pb2
from serving.config import ServerConfig
from serving.metrics import ServiceMetrics
from serving.request import FrameRequest, LabelOptions
from serving.service import LabelingService, ModelSlot
from serving.store import LabelStore, list_frames
from serving.testing import BackgroundServer, self_signed_certificate
from tests.conftest import KITTI_SAMPLE, REPO
from tests.grpc_service.conftest import (
    TORCH_FREE_SERVE,
    prometheus_sample,
    running_server,
    serve_process,
)


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


def test_the_bearer_scheme_is_case_insensitive_and_two_authorization_headers_are_refused(
    tmp_path, slot
):
    config = ServerConfig(token="s3cret")
    with running_server(slot, tmp_path / "store", config) as running:
        with grpc.insecure_channel(running.target) as channel:
            info = channel.unary_unary(
                "/detmatch.v1.AutoLabeler/GetModelInfo",
                request_serializer=lambda message: message.SerializeToString(),
                response_deserializer=lambda data: data,
            )
            request = pb2.GetModelInfoRequest()
            for scheme in ("bearer", "BEARER", "Bearer"):  # RFC 7235: any case
                info(request, metadata=[("authorization", f"{scheme} s3cret")], timeout=10)
            refused = [
                [("authorization", "Bearer s3cret"), ("authorization", "Bearer wrong")],
                [("authorization", "Bearer wrong"), ("authorization", "Bearer s3cret")],
                [("authorization", "Bearer s3cret"), ("authorization", "Bearer s3cret")],
                [("authorization", "Bearers3cret")],
                [("authorization", "Basic s3cret")],
            ]
            for metadata in refused:
                with pytest.raises(grpc.RpcError) as caught:
                    info(request, metadata=metadata, timeout=10)
                assert caught.value.code() == grpc.StatusCode.UNAUTHENTICATED, metadata


@pytest.fixture
def certificate(tmp_path):
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is needed to make a test certificate")
    return self_signed_certificate(tmp_path)


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


def test_tls_needs_both_files(certificate):
    with pytest.raises(ValueError, match="both a certificate and a key"):
        ServerConfig(tls_cert=certificate[0])


def test_metrics_count_every_request_at_the_edge(tmp_path, slot):
    """OK, INVALID_ARGUMENT, UNAUTHENTICATED, bytes that are no request and an over-size
    message are all counted, with the served model version; per-stage histograms, in-flight
    and process metrics are exported; the endpoint binds the address it is given."""
    metrics = ServiceMetrics()
    store = LabelStore(tmp_path / "store", "s0")
    config = ServerConfig(token="t0k", max_message_bytes=4 * 1024 * 1024)
    background = BackgroundServer(LabelingService(slot, store), config, metrics)
    port = background.start()
    try:
        metrics_port = metrics.serve(0, "0.0.0.0")
        with LabelingClient(f"127.0.0.1:{port}", token="t0k") as client:
            response = client.label_kitti_frame(KITTI_SAMPLE, "000000")
            not_stored = LabelOptions(store=False)
            with pytest.raises(grpc.RpcError):
                client.label_frame(
                    FrameRequest.from_arrays("../x", b"", b"", _calib(), options=not_stored)
                )
            with pytest.raises(grpc.RpcError) as over:
                client.label_frame(
                    FrameRequest.from_arrays("big", b"\0" * (5 * 1024 * 1024), b"", _calib())
                )
            assert over.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            garbage = client.channel.unary_unary("/detmatch.v1.AutoLabeler/LabelFrame")
            with pytest.raises(grpc.RpcError) as malformed:
                garbage(b"\xff\xff\xff\xff", timeout=10, metadata=client.metadata)
            assert malformed.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        with LabelingClient(f"127.0.0.1:{port}", token="wrong") as stranger:
            with pytest.raises(grpc.RpcError):
                stranger.model_info()
    finally:
        # Stopping waits for the handlers: a client can hold its status before the server
        # has counted the call, so the metrics are read after the stop.
        background.stop()
        store.close()
    text = (
        urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10)
        .read()
        .decode()
    )
    version = slot.version

    def metric(name: str, **labels: str) -> float:
        return prometheus_sample(text, name, **labels)

    for code, count in (("OK", 1), ("INVALID_ARGUMENT", 2), ("RESOURCE_EXHAUSTED", 1)):
        labels = {"method": "LabelFrame", "code": code, "model_version": version}
        assert metric("detmatch_requests_total", **labels) == count, (code, text)
    assert metric("detmatch_errors_total", method="LabelFrame", code="RESOURCE_EXHAUSTED") == 1
    assert metric("detmatch_requests_total", method="GetModelInfo", code="UNAUTHENTICATED",
                  model_version=version) == 1  # fmt: skip
    assert metric("detmatch_errors_total", method="GetModelInfo", code="UNAUTHENTICATED") == 1
    assert metric("detmatch_request_seconds_count", method="LabelFrame") == 4
    assert metric("detmatch_requests_in_flight", method="LabelFrame") == 0
    for stage in ("decode", "detector2d", "pillarize", "detector3d", "matching", "store"):
        assert metric("detmatch_stage_seconds_count", stage=stage, model_version=version) == 1
    assert metric("detmatch_labels_total", model_version=version) == len(response.labels)
    assert metric("detmatch_store_outcomes_total", outcome="created") == 1
    assert metric("detmatch_model_info", version=version) == 1
    assert metric("process_resident_memory_bytes") > 0
    assert metric("process_open_fds") > 0


def test_metrics_host_is_configurable(tmp_path, exported_repository):
    """`--metrics-host 0.0.0.0` binds every interface (it was hard-wired to 127.0.0.1)."""
    args = ("--metrics-port", "0", "--metrics-host", "0.0.0.0")
    with serve_process(exported_repository, tmp_path / "store", *args) as (process, _):
        line = ""
        while '"metrics endpoint"' not in line:
            line = process.stderr.readline()
            assert line, "no metrics endpoint line in the log"
        address = json.loads(line)["address"]
        assert address.startswith("0.0.0.0:")
        port = int(address.rsplit(":", 1)[1])
        url = f"http://127.0.0.1:{port}/metrics"
        text = urllib.request.urlopen(url, timeout=10).read().decode()
        # serve_process polled health until SERVING: the endpoint counts those calls.
        assert prometheus_sample(text, "detmatch_requests_total", method="Check", code="OK") >= 1


def _serve_command(repository, store, *args: str) -> list[str]:
    return [sys.executable, "-c", TORCH_FREE_SERVE, "--repository", str(repository),
            "--store", str(store), "--port", "0", *args]  # fmt: skip


@pytest.mark.parametrize("token", [None, "", "  "])
def test_serve_refuses_to_start_without_a_token_unless_auth_is_disabled(
    tmp_path, exported_repository, token
):
    env = {k: v for k, v in os.environ.items() if k != "DETMATCH_TOKEN"}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    if token is not None:
        env["DETMATCH_TOKEN"] = token
    done = subprocess.run(_serve_command(exported_repository, tmp_path / "store"), env=env,
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "DETMATCH_TOKEN" in done.stderr and "--no-auth" in done.stderr
    assert "listening" not in done.stdout
    env["DETMATCH_TOKEN"] = "s3cret"
    done = subprocess.run(
        _serve_command(exported_repository, tmp_path / "store", "--no-auth"),
        env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2 and "--no-auth, but $DETMATCH_TOKEN holds a token" in done.stderr


def test_serve_logs_whether_auth_and_tls_are_on(tmp_path, exported_repository, certificate):
    cert, key = certificate
    tls = ("--tls-cert", str(cert), "--tls-key", str(key))
    runs = [((), "s3cret", "bearer token", False), (("--no-auth", *tls), None, "off", True)]
    for args, token, auth, tls_on in runs:
        env = {k: v for k, v in os.environ.items() if k != "DETMATCH_TOKEN"}
        env.update(OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
        if token:
            env["DETMATCH_TOKEN"] = token
        command = _serve_command(exported_repository, tmp_path / "store", *args)
        process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True)  # fmt: skip
        try:
            starting = json.loads(process.stderr.readline())
            assert starting["message"] == "starting"
            assert (starting["auth"], starting["tls"]) == (auth, tls_on)
            warning = json.loads(process.stderr.readline())
            assert ("authentication is off" in warning["message"]) == (auth == "off")
        finally:
            process.kill()
            process.communicate(timeout=30)


def _calib():
    from detmatch.data.kitti import read_calib

    return read_calib(KITTI_SAMPLE / "training" / "calib" / "000000.txt")
