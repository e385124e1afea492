"""Prometheus metrics of the labeling service, on a registry of its own (no global state)."""

from __future__ import annotations

import grpc
from prometheus_client import CollectorRegistry, Counter, Histogram, Info, start_http_server


class ServiceMetrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "detmatch_requests", "RPCs handled", ["method", "code"], registry=self.registry
        )
        self.errors = Counter(
            "detmatch_errors", "RPCs that failed, by status code", ["method", "code"],
            registry=self.registry,
        )  # fmt: skip
        self.latency = Histogram(
            "detmatch_request_seconds",
            "RPC latency",
            ["method"],
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30),
            registry=self.registry,
        )
        self.labels = Counter("detmatch_labels", "labels produced", registry=self.registry)
        self.model_version = Info("detmatch_model", "the served model", registry=self.registry)

    def observe(self, method: str, code: grpc.StatusCode, seconds: float) -> None:
        self.requests.labels(method, code.name).inc()
        if code != grpc.StatusCode.OK:
            self.errors.labels(method, code.name).inc()
        self.latency.labels(method).observe(seconds)

    def serve(self, port: int, address: str = "127.0.0.1") -> int:
        """Start the /metrics HTTP endpoint; returns its port (port 0 picks a free one)."""
        server, _ = start_http_server(port, addr=address, registry=self.registry)
        return server.server_port
