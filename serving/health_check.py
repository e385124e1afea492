"""A client of the standard gRPC health service (`detmatch health`): the container's
HEALTHCHECK and scripts that wait for a server. grpc only, no torch.

The server reports NOT_SERVING until a model version is loaded and warmed up, and again while
it drains after SIGTERM; SERVING means LabelFrame calls will be answered.
"""

from __future__ import annotations

import time

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc


def check_health(
    target: str,
    service: str = "",
    timeout_s: float = 5.0,
    root_certificates: bytes | None = None,
    server_name: str | None = None,
) -> str:
    """The health status of `service` ("": the whole server) at target (host:port), by name:
    SERVING, NOT_SERVING, SERVICE_UNKNOWN, or UNREACHABLE when no answer came within
    timeout_s. root_certificates (PEM) switch to TLS."""
    options = [("grpc.ssl_target_name_override", server_name)] if server_name else []
    if root_certificates is not None:
        credentials = grpc.ssl_channel_credentials(root_certificates=root_certificates)
        channel = grpc.secure_channel(target, credentials, options=options)
    else:
        channel = grpc.insecure_channel(target, options=options)
    with channel:
        stub = health_pb2_grpc.HealthStub(channel)
        try:
            response = stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=timeout_s)
        except grpc.RpcError as error:
            if error.code() == grpc.StatusCode.NOT_FOUND:
                return "SERVICE_UNKNOWN"
            return "UNREACHABLE"
    return health_pb2.HealthCheckResponse.ServingStatus.Name(response.status)


def wait_until_serving(target: str, wait_s: float, poll_s: float = 0.5, **options) -> str:
    """check_health every poll_s seconds until SERVING or wait_s have passed; the last status.
    options: as check_health's."""
    deadline = time.monotonic() + wait_s
    while True:
        status = check_health(target, **options)
        if status == "SERVING" or time.monotonic() >= deadline:
            return status
        time.sleep(poll_s)
