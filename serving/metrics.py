"""Prometheus metrics of the labeling service, on a registry of its own (no global state).

Every RPC is counted at the edge (`serving.edge`), rejected ones included (UNAUTHENTICATED,
RESOURCE_EXHAUSTED, undecodable bytes, unknown methods), with the model version served when
it ended. Per-stage latency comes from each labeled frame's timings; the process collector
adds memory, CPU time and open files, the platform collector the Python version.
"""

from __future__ import annotations

import grpc
from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    PlatformCollector,
    ProcessCollector,
    start_http_server,
)

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30)
STAGE_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5)
# The stages of a LabelFrame call (the response's Timing fields).
STAGES = ("decode", "detector2d", "pillarize", "detector3d", "matching", "store")
NO_MODEL = "none"


class ServiceMetrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        labels = ["method", "code", "model_version"]
        self.requests = Counter(
            "detmatch_requests", "RPCs handled, rejected ones included", labels,
            registry=self.registry,
        )  # fmt: skip
        self.errors = Counter(
            "detmatch_errors", "RPCs that did not end OK, by status code", labels,
            registry=self.registry,
        )  # fmt: skip
        self.latency = Histogram(
            "detmatch_request_seconds", "RPC latency, from the call's start to its status",
            ["method"], buckets=LATENCY_BUCKETS, registry=self.registry,
        )  # fmt: skip
        self.in_flight = Gauge(
            "detmatch_requests_in_flight", "RPCs started and not yet ended", ["method"],
            registry=self.registry,
        )  # fmt: skip
        self.stages = Histogram(
            "detmatch_stage_seconds", "time of each stage of a labeled frame",
            ["stage", "model_version"], buckets=STAGE_BUCKETS, registry=self.registry,
        )  # fmt: skip
        self.labels = Counter(
            "detmatch_labels", "labels produced", ["model_version"], registry=self.registry
        )
        self.stored = Counter(
            "detmatch_store_outcomes", "what storing a frame did (created, unchanged, replaced)",
            ["outcome"], registry=self.registry,
        )  # fmt: skip
        self.client_errors = Counter(
            "detmatch_client_errors", "calls that failed by the client's doing, by kind (logged "
            "as rate-limited warnings)", ["kind"], registry=self.registry,
        )  # fmt: skip
        self.model_version = Info("detmatch_model", "the served model", registry=self.registry)
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)

    def observe(
        self, method: str, code: grpc.StatusCode, seconds: float, model_version: str | None
    ) -> None:
        version = model_version or NO_MODEL
        self.requests.labels(method, code.name, version).inc()
        if code != grpc.StatusCode.OK:
            self.errors.labels(method, code.name, version).inc()
        self.latency.labels(method).observe(seconds)

    def observe_frame(
        self, timings: dict[str, float], model_version: str, labels: int, outcome: str | None
    ) -> None:
        for stage in STAGES:
            if stage in timings:
                self.stages.labels(stage, model_version).observe(timings[stage])
        self.labels.labels(model_version).inc(labels)
        if outcome is not None:
            self.stored.labels(outcome).inc()

    def serve(self, port: int, address: str = "127.0.0.1") -> int:
        """Start the /metrics HTTP endpoint on address:port; returns its port (0 picks one)."""
        server, _ = start_http_server(port, addr=address, registry=self.registry)
        return server.server_port
