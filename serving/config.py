"""How `detmatch serve` runs: the address, the thread pools, message and image limits,
timeouts and keepalives, TLS and the bearer token, metrics, polling and the drain. One frozen
record the CLI builds from its flags; `LabelingServer` reads it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from serving.batching import BatchingSettings
from serving.decode import DEFAULT_MAX_IMAGE_PIXELS, DEFAULT_MAX_POINTS
from serving.edge import DEFAULT_INFLIGHT_BYTES, EdgeSettings
from serving.sessions import SessionSettings

# A full KITTI frame is about 3 MB (1.9 MB of points, 1 MB of PNG). 48 MiB holds the largest
# frame the other limits admit (2,000,000 points, 32 MB, and a 4K image) and no more: gRPC reads
# every message under this cap into memory before the server can refuse it, so this cap, not
# the byte budget, bounds what uploads in progress hold (BENCHMARKS.md, "Heavy and stalled
# clients"); a message over it is refused as its first bytes arrive.
DEFAULT_MAX_MESSAGE_BYTES = 48 * 1024 * 1024
# A call's whole header block (HPACK-decoded, with gRPC's own headers): room for a token of a
# few kilobytes.
MAX_HEADER_BYTES = 16 * 1024


@dataclass(frozen=True)
class ServerConfig:
    address: str = "127.0.0.1:0"
    workers: int = 4  # inference threads: frames decoded and labeled at once
    # Dynamic batching (serving.batching; Triton's names): frames labeled in one pair of graph
    # calls, 1: off; how long the oldest waits for others.
    max_batch_size: int = 1
    max_queue_delay_us: int = 2000
    store_threads: int = 8  # I/O threads writing frames to the label store
    threads: int = 0  # onnxruntime intra-op threads per run; 0: the CPUs this process may use
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS  # checked on the header, before decoding
    max_points: int = DEFAULT_MAX_POINTS  # LiDAR points per frame; INVALID_ARGUMENT beyond
    max_concurrent_rpcs: int = 64  # labeling calls at once, counted once their message arrived
    # Bytes the labeling calls in flight may hold (3x their messages: edge.MESSAGE_COST); a
    # call that does not fit waits budget_wait_s, then gets RESOURCE_EXHAUSTED.
    max_inflight_bytes: int = DEFAULT_INFLIGHT_BYTES
    budget_wait_s: float = 5.0
    max_uploads_per_peer: int = 16  # labeling requests one connection may have uploading
    max_streams_per_connection: int = 32  # HTTP/2 SETTINGS_MAX_CONCURRENT_STREAMS
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
        for name in ("workers", "store_threads", "max_message_bytes", "max_concurrent_rpcs",
                     "max_points", "max_streams_per_connection"):  # fmt: skip
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_batch_size > self.workers:
            raise ValueError(
                f"max_batch_size {self.max_batch_size} exceeds workers {self.workers}: each "
                "frame waiting in a batch holds an inference thread"
            )
        self.batching()  # checks the batching values
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0: every CPU), got {self.threads}")
        if self.max_image_pixels < 1:
            raise ValueError(f"max_image_pixels must be >= 1, got {self.max_image_pixels}")
        if self.token is not None and not self.token:
            raise ValueError("token: empty; give a token, or None for no authentication")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("TLS needs both a certificate and a key")

    def edge(self) -> EdgeSettings:
        return EdgeSettings(
            self.token, self.max_concurrent_rpcs, self.receive_timeout_s,
            max_inflight_bytes=self.max_inflight_bytes, budget_wait_s=self.budget_wait_s,
            max_uploads_per_peer=self.max_uploads_per_peer,
        )  # fmt: skip

    def channel_options(self) -> list[tuple[str, int]]:
        def ms(seconds: float) -> int:
            return int(seconds * 1000)

        return [
            ("grpc.max_receive_message_length", self.max_message_bytes),
            ("grpc.max_send_message_length", self.max_message_bytes),
            # A second server on a busy port must fail to bind, not share it silently.
            ("grpc.so_reuseport", 0),
            ("grpc.max_concurrent_streams", self.max_streams_per_connection),
            # One limit for a call's headers: under it a call reaches authentication, over it
            # gRPC refuses it (RESOURCE_EXHAUSTED). gRPC's own default refuses header blocks
            # between 8 and 16 KiB at random, so the same token would pass on one call and not
            # on the next.
            ("grpc.max_metadata_size", MAX_HEADER_BYTES),
            ("grpc.absolute_max_metadata_size", MAX_HEADER_BYTES),
            ("grpc.keepalive_time_ms", ms(self.keepalive_s)),
            ("grpc.keepalive_timeout_ms", ms(self.keepalive_timeout_s)),
            ("grpc.keepalive_permit_without_calls", 1),
            ("grpc.http2.min_ping_interval_without_data_ms", 10_000),
            ("grpc.max_connection_idle_ms", ms(self.max_connection_idle_s)),
            ("grpc.max_connection_age_ms", ms(self.max_connection_age_s)),
            ("grpc.max_connection_age_grace_ms", ms(self.max_connection_age_grace_s)),
        ]

    def batching(self) -> BatchingSettings:
        return BatchingSettings(self.max_batch_size, self.max_queue_delay_us)

    def session_settings(self) -> SessionSettings:
        return SessionSettings(intra_op_threads=self.threads)
