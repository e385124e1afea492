"""How `detmatch serve` runs: the address, the thread pools, message and image limits,
timeouts and keepalives, TLS and the bearer token, metrics, polling and the drain. One frozen
record the CLI builds from its flags; `LabelingServer` reads it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from serving.decode import DEFAULT_MAX_IMAGE_PIXELS
from serving.edge import EdgeSettings
from serving.sessions import SessionSettings

# A full KITTI frame is about 3 MB (1.9 MB of points, 1 MB of PNG); 64 MiB fits it 20 times.
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024


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
