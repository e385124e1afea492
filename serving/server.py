"""The gRPC auto-labeling server's lifecycle: create (bind), start, stop (drain), and `serve`,
which is `detmatch serve`. asyncio (`grpc.aio`), the AutoLabeler servicer (serving.servicer)
over `LabelingService`, the standard health and reflection services, optional TLS and
bearer-token auth, Prometheus metrics, hot swap and a graceful shutdown on SIGTERM.
Torch-free.

Threads: the event loop receives and answers every call, so a slow or stalled client holds no
thread and health and reflection always answer. Decoding and labeling run on an inference
pool of `workers` threads (the CPU-bound part, bounded), storing on an I/O pool of
`store_threads` (file writes and fsyncs, which wait on the disk, not the CPU).
`serving.edge` counts, authenticates, admits and parses every call.

`LabelingServer.create(service, config)` binds (port 0 picks a free port) without starting;
serving.testing's `BackgroundServer` runs one on an event loop of its own thread (tests,
benchmarks, embedding); `serve(...)` is `detmatch serve`.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from serving import memory
from serving.batching import batcher_for
from serving.config import ServerConfig
from serving.edge import EdgeInterceptor
from serving.labeler import Labeler
from serving.metrics import ServiceMetrics
from serving.service import LabelingService, ModelSlot
from serving.servicer import SERVICE_NAME, AutoLabelerServicer, pb2_grpc
from serving.store import LabelStore
from serving.watcher import RepositoryWatcher

log = logging.getLogger("detmatch.serving")


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
        edge = EdgeInterceptor(
            config.edge(), metrics, lambda: slot.version, f"/{SERVICE_NAME}/",
            frozenset({f"/{SERVICE_NAME}/LabelFrame"}),
        )  # fmt: skip
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
                          "max_batch_size": config.max_batch_size,
                          "max_concurrent_rpcs": config.max_concurrent_rpcs,
                          "repository": str(repository), "store": str(store_root),
                          "shard": shard}},
    )  # fmt: skip
    if config.token is None:
        log.warning("authentication is off (--no-auth): any client that reaches the port may "
                    "label and store frames")  # fmt: skip
    slot = ModelSlot()
    store = LabelStore(store_root, shard)
    batcher = batcher_for(config.batching())
    service = LabelingService(slot, store, config.max_image_pixels, config.max_points, batcher)
    metrics = ServiceMetrics()
    try:
        server = await LabelingServer.create(service, config, metrics)
    except BaseException:
        if batcher is not None:
            batcher.close()
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
    if batcher is not None:
        batcher.close()
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
