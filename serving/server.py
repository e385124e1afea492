"""The gRPC auto-labeling server: a thin servicer over `LabelingService`, the standard health
and reflection services, optional TLS and bearer-token auth, Prometheus metrics, hot swap and
a graceful shutdown on SIGTERM. Torch-free.

`create_server(service, config) -> (server, port, health)` binds (port 0 picks a free port) and
does not start; `serve(config)` is `detmatch serve`.
"""

from __future__ import annotations

import hmac
import json
import logging
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from serving.errors import status_for
from serving.metrics import ServiceMetrics
from serving.proto import load as load_stubs
from serving.serialize import BOX_2D_FIELDS, BOX_3D_FIELDS, label_records
from serving.service import LabelingService, LabelOptions, LabelResult, ModelSlot
from serving.store import LabelStore
from serving.watcher import RepositoryWatcher

pb2, pb2_grpc = load_stubs()
log = logging.getLogger("detmatch.serving")

SERVICE_NAME = pb2.DESCRIPTOR.services_by_name["AutoLabeler"].full_name
HEALTH_PREFIX = f"/{health.SERVICE_NAME}/"
# A full KITTI frame is about 3 MB (1.9 MB of points, 1 MB of PNG); 64 MiB fits it 20 times.
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024


@dataclass(frozen=True)
class ServerConfig:
    address: str = "127.0.0.1:0"
    workers: int = 4
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    tls_cert: Path | None = None  # PEM server certificate (chain); with tls_key
    tls_key: Path | None = None
    token: str | None = None  # bearer token clients must send; None: no auth
    metrics_port: int | None = None  # Prometheus endpoint on this port; None: off
    metrics_address: str = "127.0.0.1"
    poll_s: float = 2.0  # how often the model repository is checked
    grace_s: float = 30.0  # how long in-flight calls may run after SIGTERM


class AutoLabelerServicer(pb2_grpc.AutoLabelerServicer):
    """Protos in and out; everything else is LabelingService's."""

    def __init__(self, service: LabelingService, metrics: ServiceMetrics) -> None:
        self.service = service
        self.metrics = metrics

    def LabelFrame(self, request, context):  # noqa: N802 - gRPC's method name
        start = time.perf_counter()
        code = grpc.StatusCode.OK
        version = None
        try:
            if context.time_remaining() is not None and context.time_remaining() <= 0:
                code = grpc.StatusCode.DEADLINE_EXCEEDED
                context.abort(code, "deadline exceeded before labeling started")
            options = request.options
            result = self.service.label_frame(
                request.frame_id,
                request.image,
                request.points,
                request.calibration.p2,
                request.calibration.r0_rect,
                request.calibration.tr_velo_to_cam,
                LabelOptions(
                    score_threshold_2d=_optional(options, "score_threshold_2d"),
                    score_threshold_3d=_optional(options, "score_threshold_3d"),
                    tau_hung=_optional(options, "tau_hung"),
                    store=options.store if options.HasField("store") else True,
                ),
            )
            self.metrics.labels.inc(len(result.result))
            version = result.result.model_version
            return _response(result)
        except Exception as error:  # noqa: BLE001 - status_for decides; abort re-raises
            if code != grpc.StatusCode.OK:
                raise
            code, message = status_for(error)
            if code == grpc.StatusCode.INTERNAL:
                log.exception("LabelFrame failed")
            context.abort(code, message)
        finally:
            elapsed = time.perf_counter() - start
            self.metrics.observe("LabelFrame", code, elapsed)
            fields = {
                "frame_id": request.frame_id[:64],
                "code": code.name,
                "seconds": round(elapsed, 4),
                "model_version": version,
            }
            log.info("LabelFrame", extra={"fields": fields})

    def GetModelInfo(self, request, context):  # noqa: N802 - gRPC's method name
        start = time.perf_counter()
        code = grpc.StatusCode.OK
        try:
            info = self.service.model_info()
            return pb2.ModelInfo(
                version=info["version"],
                classes=info["classes"],
                score_threshold_2d=info["score_threshold_2d"],
                score_threshold_3d=info["score_threshold_3d"],
                tau_hung=info["tau_hung"],
                tau_3d_outside_view=info["tau_3d_outside_view"],
                metrics_json=json.dumps(info["metrics"]),
            )
        except Exception as error:  # noqa: BLE001 - status_for decides
            code, message = status_for(error)
            context.abort(code, message)
        finally:
            self.metrics.observe("GetModelInfo", code, time.perf_counter() - start)


class BearerTokenInterceptor(grpc.ServerInterceptor):
    """UNAUTHENTICATED unless `authorization: Bearer <token>` matches; health is exempt."""

    def __init__(self, token: str) -> None:
        self._expected = f"Bearer {token}".encode()

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None or handler_call_details.method.startswith(HEALTH_PREFIX):
            return handler
        metadata = dict(handler_call_details.invocation_metadata or ())
        given = str(metadata.get("authorization", "")).encode()
        if hmac.compare_digest(given, self._expected):
            return handler
        return _denial(handler)


def _denial(handler: grpc.RpcMethodHandler) -> grpc.RpcMethodHandler:
    """A handler of the same kind as handler that answers UNAUTHENTICATED."""

    def deny(request, context):
        context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or invalid bearer token")

    serializers = {
        "request_deserializer": handler.request_deserializer,
        "response_serializer": handler.response_serializer,
    }
    if handler.request_streaming and handler.response_streaming:
        return grpc.stream_stream_rpc_method_handler(deny, **serializers)
    if handler.request_streaming:
        return grpc.stream_unary_rpc_method_handler(deny, **serializers)
    if handler.response_streaming:
        return grpc.unary_stream_rpc_method_handler(deny, **serializers)
    return grpc.unary_unary_rpc_method_handler(deny, **serializers)


def create_server(
    service: LabelingService, config: ServerConfig, metrics: ServiceMetrics | None = None
) -> tuple[grpc.Server, int, health.HealthServicer]:
    """A bound, not yet started server; health says NOT_SERVING until a model is served."""
    from concurrent import futures

    metrics = metrics or ServiceMetrics()
    interceptors = [BearerTokenInterceptor(config.token)] if config.token else []
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=config.workers, thread_name_prefix="rpc"),
        interceptors=interceptors,
        options=[
            ("grpc.max_receive_message_length", config.max_message_bytes),
            ("grpc.max_send_message_length", config.max_message_bytes),
        ],
    )
    pb2_grpc.add_AutoLabelerServicer_to_server(AutoLabelerServicer(service, metrics), server)
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(
        (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME), server
    )

    def on_swap(labeler) -> None:
        metrics.model_version.info({"version": labeler.version})
        for name in ("", SERVICE_NAME):
            health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)

    for name in ("", SERVICE_NAME):
        status = health_pb2.HealthCheckResponse.NOT_SERVING
        if service.slot.version is not None:
            status = health_pb2.HealthCheckResponse.SERVING
        health_servicer.set(name, status)
    service.slot.listeners.append(on_swap)
    if config.tls_cert is not None or config.tls_key is not None:
        if config.tls_cert is None or config.tls_key is None:
            raise ValueError("TLS needs both a certificate and a key")
        credentials = grpc.ssl_server_credentials(
            [(Path(config.tls_key).read_bytes(), Path(config.tls_cert).read_bytes())]
        )
        port = server.add_secure_port(config.address, credentials)
    else:
        port = server.add_insecure_port(config.address)
    if port == 0:
        raise OSError(f"cannot bind {config.address}")
    return server, port, health_servicer


def serve(
    repository: Path,
    store: Path,
    config: ServerConfig,
    shard: str = "default",
    ready: threading.Event | None = None,
) -> None:
    """`detmatch serve`: run until SIGTERM or SIGINT, then drain (health NOT_SERVING first)."""
    slot = ModelSlot()
    service = LabelingService(slot, LabelStore(store, shard))
    metrics = ServiceMetrics()
    server, port, health_servicer = create_server(service, config, metrics)
    if config.metrics_port is not None:
        metrics_port = metrics.serve(config.metrics_port, config.metrics_address)
        log.info("metrics endpoint", extra={"fields": {"port": metrics_port}})
    server.start()
    host = config.address.rsplit(":", 1)[0]
    log.info("listening", extra={"fields": {"address": f"{host}:{port}"}})
    print(f"listening on {host}:{port}", flush=True)
    stopping = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stopping.set())
    watcher = RepositoryWatcher(repository, slot, poll_s=config.poll_s)
    watcher.check()
    watcher.start()
    if ready is not None:
        ready.set()
    stopping.wait()
    watcher.stop()
    shutdown(server, health_servicer, config.grace_s)
    service.store.close()
    log.info("stopped")


def shutdown(server: grpc.Server, health_servicer: health.HealthServicer, grace_s: float) -> None:
    """Drain: health NOT_SERVING (load balancers stop routing here), new calls refused, calls
    in flight given grace_s seconds to finish."""
    log.info("draining", extra={"fields": {"grace_s": grace_s}})
    health_servicer.enter_graceful_shutdown()
    server.stop(grace_s).wait()


def _optional(message, name: str) -> float | None:
    return getattr(message, name) if message.HasField(name) else None


def _response(result: LabelResult):
    rows = []
    for record in label_records(result.result):
        row = pb2.Label(
            class_name=record.class_3d,
            box_3d=pb2.Box3D(**dict(zip(BOX_3D_FIELDS, record.box_3d, strict=True))),
            score_3d=record.score_3d,
            provenance=int(record.provenance),
        )
        if record.box_2d is not None:
            row.class_name_2d = record.class_2d
            row.box_2d.CopyFrom(pb2.Box2D(**dict(zip(BOX_2D_FIELDS, record.box_2d, strict=True))))
            row.score_2d = record.score_2d
            row.match_cost = record.cost
        rows.append(row)
    t = result.timings
    return pb2.LabelFrameResponse(
        frame_id=result.frame_id,
        model_version=result.result.model_version,
        labels=rows,
        stored=result.stored is not None,
        timing=pb2.Timing(
            total_s=t.get("total", 0.0),
            decode_s=t.get("decode", 0.0),
            detector2d_s=t.get("detector2d", 0.0),
            pillarize_s=t.get("pillarize", 0.0),
            detector3d_s=t.get("detector3d", 0.0),
            matching_s=t.get("matching", 0.0),
            store_s=t.get("store", 0.0),
        ),
    )
