"""What tests and benchmarks of the service share: `BackgroundServer`, a `LabelingServer` on an
event loop of its own thread, and a self-signed TLS certificate. Waiting for a server to be
SERVING is serving.health_check.wait_until_serving.
"""

from __future__ import annotations

import asyncio
import subprocess
import threading
from pathlib import Path

from serving.config import ServerConfig
from serving.metrics import ServiceMetrics
from serving.server import LabelingServer
from serving.service import LabelingService


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


def self_signed_certificate(directory: Path) -> tuple[Path, Path]:
    """(cert.pem, key.pem) in directory, made by the openssl command unless present: a
    certificate for localhost and 127.0.0.1, valid for a day."""
    cert, key = directory / "cert.pem", directory / "key.pem"
    if not cert.is_file():
        subprocess.run(
            ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
             "-keyout", str(key), "-out", str(cert), "-subj", "/CN=localhost",
             "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
            check=True, capture_output=True,
        )  # fmt: skip
    return cert, key
