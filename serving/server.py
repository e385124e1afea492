"""The gRPC auto-labeling server: asyncio (`grpc.aio`), a thin servicer over `LabelingService`,
the standard health and reflection services, optional TLS and bearer-token auth, Prometheus
metrics, hot swap and a graceful shutdown on SIGTERM. Torch-free.

Threads: the event loop receives and answers every call, so a slow or stalled client holds no
thread and health and reflection always answer. Decoding and labeling run on an inference
pool of `workers` threads (the CPU-bound part, bounded), storing on an I/O pool (file writes
and fsyncs, which wait on the disk, not the CPU). `serving.edge` counts, authenticates,
admits and parses every call.

`LabelingServer.create(service, config)` binds (port 0 picks a free port) without starting;
`BackgroundServer` runs one on an event loop of its own thread (tests, benchmarks,
embedding); `serve(...)` is `detmatch serve`.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from serving import memory
from serving.decode import DEFAULT_MAX_IMAGE_PIXELS
from serving.edge import EdgeInterceptor, EdgeSettings, call_fields
from serving.errors import status_for
from serving.labeler import Labeler
from serving.metrics import ServiceMetrics
from serving.proto import load as load_stubs
from serving.serialize import BOX_2D_FIELDS, BOX_3D_FIELDS, label_records
from serving.service import LabelingService, LabelOptions, LabelResult, ModelSlot
from serving.sessions import SessionSettings
from serving.store import LabelStore, StoreOutcome
from serving.watcher import RepositoryWatcher

pb2, pb2_grpc = load_stubs()
log = logging.getLogger("detmatch.serving")

SERVICE_NAME = pb2.DESCRIPTOR.services_by_name["AutoLabeler"].full_name
# A full KITTI frame is about 3 MB (1.9 MB of points, 1 MB of PNG); 64 MiB fits it 20 times.
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
OUTCOMES = {
    StoreOutcome.CREATED: pb2.STORE_OUTCOME_CREATED,
    StoreOutcome.UNCHANGED: pb2.STORE_OUTCOME_UNCHANGED,
    StoreOutcome.REPLACED: pb2.STORE_OUTCOME_REPLACED,
}


@dataclass(frozen=True)
class ServerConfig:
    address: str = "127.0.0.1:0"
    workers: int = 4  # inference threads: frames decoded and labeled at once
    store_threads: int = 8  # I/O threads writing frames to the label store
    threads: int = 0  # onnxruntime intra-op threads per run; 0: the CPUs this process may use
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS  # checked on the header, before decoding
    max_concurrent_rpcs: int = 64  # labeling calls at once; RESOURCE_EXHAUSTED beyond
    receive_timeout_s: float = 30.0  # a request message must arrive within this
    keepalive_s: float = 60.0  # ping an idle connection this often ...
    keepalive_timeout_s: float = 20.0  # ... and drop it when the ping is not answered
    max_connection_idle_s: float = 300.0  # close connections without calls this long
    max_connection_age_s: float = 1800.0  # then ask clients to reconnect (load balancing) ...
    max_connection_age_grace_s: float = 60.0  # ... giving calls in flight this long
    tls_cert: Path | None = None  # PEM server certificate (chain); with tls_key
    tls_key: Path | None = None
    token: str | None = None  # bearer token clients must send; None: no auth
    metrics_port: int | None = None  # Prometheus endpoint on this port; None: off
    metrics_address: str = "127.0.0.1"
    poll_s: float = 2.0  # how often the model repository is checked
    trim_memory_s: float = 5.0  # return freed memory to the system this often (0: never)
    grace_s: float = 30.0  # how long in-flight calls may run after SIGTERM

    def __post_init__(self) -> None:
        for name in ("workers", "store_threads", "max_message_bytes", "max_concurrent_rpcs"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0: every CPU), got {self.threads}")
        if self.max_image_pixels < 1:
            raise ValueError(f"max_image_pixels must be >= 1, got {self.max_image_pixels}")
        if self.token is not None and not self.token:
            raise ValueError("token: empty; give a token, or None for no authentication")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("TLS needs both a certificate and a key")

    def edge(self) -> EdgeSettings:
        return EdgeSettings(self.token, self.max_concurrent_rpcs, self.receive_timeout_s)

    def channel_options(self) -> list[tuple[str, int]]:
        def ms(seconds: float) -> int:
            return int(seconds * 1000)

        return [
            ("grpc.max_receive_message_length", self.max_message_bytes),
            ("grpc.max_send_message_length", self.max_message_bytes),
            # A second server on a busy port must fail to bind, not share it silently.
            ("grpc.so_reuseport", 0),
            ("grpc.keepalive_time_ms", ms(self.keepalive_s)),
            ("grpc.keepalive_timeout_ms", ms(self.keepalive_timeout_s)),
            ("grpc.keepalive_permit_without_calls", 1),
            ("grpc.http2.min_ping_interval_without_data_ms", 10_000),
            ("grpc.max_connection_idle_ms", ms(self.max_connection_idle_s)),
            ("grpc.max_connection_age_ms", ms(self.max_connection_age_s)),
            ("grpc.max_connection_age_grace_ms", ms(self.max_connection_age_grace_s)),
        ]

    def session_settings(self) -> SessionSettings:
        return SessionSettings(intra_op_threads=self.threads)


class AutoLabelerServicer(pb2_grpc.AutoLabelerServicer):
    """Protos in and out; everything else is LabelingService's."""

    def __init__(
        self,
        service: LabelingService,
        metrics: ServiceMetrics,
        inference: ThreadPoolExecutor,
        storage: ThreadPoolExecutor,
    ) -> None:
        self.service = service
        self.metrics = metrics
        self.inference = inference
        self.storage = storage

    async def LabelFrame(self, request, context):  # noqa: N802 - gRPC's method name
        fields = call_fields()
        fields["frame_id"] = request.frame_id[:64]
        if request.namespace:
            fields["namespace"] = request.namespace[:64]
        if context.time_remaining() is not None and context.time_remaining() <= 0:
            await context.abort(
                grpc.StatusCode.DEADLINE_EXCEEDED, "deadline exceeded before labeling started"
            )
        loop = asyncio.get_running_loop()
        options = request.options
        label_options = LabelOptions(
            score_threshold_2d=_optional(options, "score_threshold_2d"),
            score_threshold_3d=_optional(options, "score_threshold_3d"),
            tau_hung=_optional(options, "tau_hung"),
            store=options.store if options.HasField("store") else True,
        )
        start = time.perf_counter()
        labeled = await loop.run_in_executor(
            self.inference, _status_or, self._decode_and_label, request, label_options
        )
        if isinstance(labeled, _Failure):
            await context.abort(labeled.code, labeled.message)
        frame, result, decode_s = labeled
        stored_at = time.perf_counter()
        stored = None
        if label_options.store and self.service.store is not None:
            stored = await loop.run_in_executor(
                self.storage, _status_or, self.service.store_labels, frame, result
            )
            if isinstance(stored, _Failure):
                await context.abort(stored.code, stored.message)
        end = time.perf_counter()
        timings = {**result.timings, "decode": decode_s, "store": end - stored_at,
                   "total": end - start}  # fmt: skip
        outcome = None if stored is None else stored.outcome.value
        self.metrics.observe_frame(timings, result.model_version, len(result), outcome)
        fields.update(labels=len(result), store=outcome or "not stored")
        return _response(LabelResult(frame.namespace, frame.frame_id, result, stored, timings))

    def _decode_and_label(self, request, options: LabelOptions):
        start = time.perf_counter()
        calibration = request.calibration
        frame = self.service.decode(
            request.frame_id,
            request.image,
            request.points,
            calibration.p2,
            calibration.r0_rect,
            calibration.tr_velo_to_cam,
            request.namespace if request.HasField("namespace") else None,
        )
        decoded = time.perf_counter()
        return frame, self.service.label(frame, options), decoded - start

    async def GetModelInfo(self, request, context):  # noqa: N802 - gRPC's method name
        try:
            info = self.service.model_info()
        except Exception as error:  # noqa: BLE001 - status_for decides
            code, message = status_for(error)
            await context.abort(code, message)
        return pb2.ModelInfo(
            version=info["version"],
            classes=info["classes"],
            score_threshold_2d=info["score_threshold_2d"],
            score_threshold_3d=info["score_threshold_3d"],
            tau_hung=info["tau_hung"],
            tau_3d_outside_view=info["tau_3d_outside_view"],
            tau_3d_unmatched=info["tau_3d_unmatched"],
            metrics_json=json.dumps(info["metrics"]),
        )


@dataclass(frozen=True)
class _Failure:
    code: grpc.StatusCode
    message: str


def _status_or(function, *args):
    """function(*args), or the _Failure its exception maps to. Errors cross from the worker
    thread as values: an exception would carry its traceback, and with it the request and
    the frame's arrays, until the garbage collector breaks the cycle (measured: the RSS of a
    server answering bad calibrations grew by about 10 MB per call)."""
    try:
        return function(*args)
    except Exception as error:  # noqa: BLE001 - status_for decides
        code, message = status_for(error)
        if code == grpc.StatusCode.INTERNAL:
            log.exception("LabelFrame failed")
        return _Failure(code, message)


class LabelingServer:
    """A bound aio server, its health service and its thread pools. Create it with `create`
    inside the event loop that will run it."""

    def __init__(self, server, port, health_servicer, pools, service, config) -> None:
        self.server: grpc.aio.Server = server
        self.port: int = port
        self.health: health.aio.HealthServicer = health_servicer
        self.service: LabelingService = service
        self.config: ServerConfig = config
        self._pools: tuple[ThreadPoolExecutor, ...] = pools
        self._loop = asyncio.get_running_loop()
        self._on_swap = None
        self._trimmer: asyncio.Task | None = None

    @classmethod
    async def create(
        cls,
        service: LabelingService,
        config: ServerConfig,
        metrics: ServiceMetrics | None = None,
    ) -> LabelingServer:
        """Bound, not started; health says NOT_SERVING until a model is served. OSError when
        the address cannot be bound (in use, or not an address of this host)."""
        metrics = metrics or ServiceMetrics()
        slot = service.slot
        edge = EdgeInterceptor(config.edge(), metrics, lambda: slot.version, f"/{SERVICE_NAME}/")
        server = grpc.aio.server(interceptors=[edge], options=config.channel_options())
        inference = ThreadPoolExecutor(config.workers, thread_name_prefix="inference")
        storage = ThreadPoolExecutor(config.store_threads, thread_name_prefix="store")
        servicer = AutoLabelerServicer(service, metrics, inference, storage)
        pb2_grpc.add_AutoLabelerServicer_to_server(servicer, server)
        health_servicer = health.aio.HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
        reflection.enable_server_reflection(
            (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME), server
        )
        serving = slot.version is not None
        for name in ("", SERVICE_NAME):
            await health_servicer.set(name, _status(serving))
        if serving:
            metrics.model_version.info({"version": slot.version})
        try:
            port = _bind(server, config)
        except BaseException:
            inference.shutdown(wait=False)
            storage.shutdown(wait=False)
            raise
        labeling = cls(server, port, health_servicer, (inference, storage), service, config)
        loop = labeling._loop

        def on_swap(labeler: Labeler) -> None:  # called on the watcher's thread
            metrics.model_version.info({"version": labeler.version})
            loop.call_soon_threadsafe(lambda: loop.create_task(labeling._set_serving()))

        labeling._on_swap = on_swap
        slot.listeners.append(on_swap)
        return labeling

    async def _set_serving(self) -> None:
        for name in ("", SERVICE_NAME):
            await self.health.set(name, health_pb2.HealthCheckResponse.SERVING)

    async def start(self) -> None:
        await self.server.start()
        if self.config.trim_memory_s > 0:
            self._trimmer = self._loop.create_task(self._trim_memory())

    async def _trim_memory(self) -> None:
        while True:
            await asyncio.sleep(self.config.trim_memory_s)
            await self._loop.run_in_executor(None, memory.trim)

    async def stop(self, grace_s: float | None) -> None:
        """Drain: health NOT_SERVING (load balancers stop routing here), new calls refused,
        calls in flight given grace_s seconds to finish (None: cancelled now)."""
        log.info("draining", extra={"fields": {"grace_s": grace_s}})
        if self._trimmer is not None:
            self._trimmer.cancel()
        await self.health.enter_graceful_shutdown()
        if self._on_swap in self.service.slot.listeners:
            self.service.slot.listeners.remove(self._on_swap)
        await self.server.stop(grace_s)
        for pool in self._pools:
            pool.shutdown(wait=True)


class BackgroundServer:
    """A LabelingServer on an event loop of its own thread: start() binds and starts it and
    returns its port; stop() drains it. For tests, benchmarks and embedding."""

    def __init__(
        self,
        service: LabelingService,
        config: ServerConfig,
        metrics: ServiceMetrics | None = None,
    ) -> None:
        self.service, self.config, self.metrics = service, config, metrics or ServiceMetrics()
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="grpc-aio", daemon=True)
        self.server: LabelingServer | None = None

    def start(self) -> int:
        self._thread.start()
        try:
            self.server = self.call(LabelingServer.create(self.service, self.config, self.metrics))
            self.call(self.server.start())
        except BaseException:
            self._close_loop()
            raise
        return self.server.port

    def call(self, coroutine, timeout_s: float | None = 60.0):
        """Run a coroutine on the server's loop and wait for its result."""
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result(timeout_s)

    def stop(self, grace_s: float | None = None) -> None:
        if self.server is not None:
            self.call(self.server.stop(grace_s), timeout_s=None)
        self._close_loop()

    def _close_loop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout=30)
        self.loop.close()

    def __enter__(self) -> BackgroundServer:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def serve(
    repository: Path,
    store: Path,
    config: ServerConfig,
    shard: str = "default",
    ready: threading.Event | None = None,
) -> None:
    """`detmatch serve`: run until SIGTERM or SIGINT, then drain (health NOT_SERVING first)."""
    asyncio.run(_serve(repository, store, config, shard, ready))


async def _serve(
    repository: Path, store_root: Path, config: ServerConfig, shard: str, ready
) -> None:
    loop = asyncio.get_running_loop()
    settings = config.session_settings()
    log.info(
        "starting",
        extra={"fields": {"address": config.address, "auth": "bearer token" if config.token
                          else "off", "tls": config.tls_cert is not None,
                          "workers": config.workers, "onnxruntime_threads": settings.threads,
                          "max_concurrent_rpcs": config.max_concurrent_rpcs,
                          "repository": str(repository), "store": str(store_root),
                          "shard": shard}},
    )  # fmt: skip
    if config.token is None:
        log.warning("authentication is off (--no-auth): any client that reaches the port may "
                    "label and store frames")  # fmt: skip
    slot = ModelSlot()
    store = LabelStore(store_root, shard)
    service = LabelingService(slot, store, config.max_image_pixels)
    metrics = ServiceMetrics()
    try:
        server = await LabelingServer.create(service, config, metrics)
    except BaseException:
        store.close()
        raise
    if config.metrics_port is not None:
        metrics_port = metrics.serve(config.metrics_port, config.metrics_address)
        log.info("metrics endpoint", extra={"fields": {
            "address": format_address(config.metrics_address, metrics_port)}})  # fmt: skip
    await server.start()
    host = config.address.rsplit(":", 1)[0]
    address = f"{host}:{server.port}"
    log.info("listening", extra={"fields": {"address": address}})
    print(f"listening on {address}", flush=True)
    stopping = asyncio.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stopping.set)
    watcher = RepositoryWatcher(
        repository, slot, poll_s=config.poll_s, load=partial(Labeler, settings=settings)
    )
    await loop.run_in_executor(None, watcher.check)  # health answers NOT_SERVING meanwhile
    watcher.start()
    if ready is not None:
        ready.set()
    await stopping.wait()
    await loop.run_in_executor(None, watcher.stop)
    await server.stop(config.grace_s)
    store.close()
    log.info("stopped")


def format_address(host: str, port: int) -> str:
    """host:port, an IPv6 host in brackets ([::]:50051)."""
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"{host}:{port}"


def _bind(server: grpc.aio.Server, config: ServerConfig) -> int:
    try:
        if config.tls_cert is not None:
            credentials = grpc.ssl_server_credentials(
                [(Path(config.tls_key).read_bytes(), Path(config.tls_cert).read_bytes())]
            )
            port = server.add_secure_port(config.address, credentials)
        else:
            port = server.add_insecure_port(config.address)
    except RuntimeError as error:
        raise OSError(f"cannot bind {config.address}: {error}") from None
    if port == 0:
        raise OSError(f"cannot bind {config.address}: in use, or not an address of this host")
    return port


def _status(serving: bool) -> int:
    if serving:
        return health_pb2.HealthCheckResponse.SERVING
    return health_pb2.HealthCheckResponse.NOT_SERVING


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
    stored = result.stored
    return pb2.LabelFrameResponse(
        frame_id=result.frame_id,
        namespace=result.namespace,
        model_version=result.result.model_version,
        labels=rows,
        stored=stored is not None,
        store_outcome=pb2.STORE_OUTCOME_NOT_STORED if stored is None else OUTCOMES[stored.outcome],
        previous_model_version=(stored and stored.previous_version) or "",
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
