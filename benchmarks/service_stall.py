"""Stalled and idle connections against `detmatch serve`: health and a normal client must not
notice them.

    python -m benchmarks.service_stall [--workers 2] [--seconds 10] [--config configs/tiny.toml]

A stalled stream is what a broken or hostile client does: HTTP/2 request headers of
LabelFrame and the first bytes of a message announcing 1 MB, then nothing (written with the
`h2` library, since no gRPC client can stop half way through a message). An idle connection
is an HTTP/2 connection without a call. Phase 1 measures a normal client (one LabelFrame
after another, store off) and health checks (every 20 ms on a connection of their own) on
an otherwise idle server; phase 2 the same with 4 x --workers stalled streams and as many
idle connections open. Figures: health latency p50 / p99 / max in each phase (target:
under 100 ms), the normal client's throughput in phase 2 over phase 1, and what the stalled
streams got once the server's receive timeout (--receive-timeout-s) passed. The sync server
this replaced stopped answering anything, health included, once --workers streams stalled.
"""

from __future__ import annotations

import json
import socket
import tempfile
import threading
import time
from pathlib import Path

import grpc

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import (
    percentiles,
    prepare_repository,
    sample_requests,
    serve,
)

LABEL_FRAME = "/detmatch.v1.AutoLabeler/LabelFrame"


class StalledStream:
    """One HTTP/2 connection holding `streams` gRPC calls that each sent their headers (with
    `headers` added: an authorization header, say) and `sent` bytes of a message announced as
    `declared` bytes long, then stop (no END_STREAM). `stream_id` is the first call's."""

    def __init__(
        self,
        target: str,
        path: str = LABEL_FRAME,
        declared: int = 1_000_000,
        sent: int = 100,
        *,
        streams: int = 1,
        headers: list[tuple[str | bytes, str | bytes]] = (),
    ) -> None:
        import h2.config
        import h2.connection

        host, port = target.rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=30)
        self.connection = h2.connection.H2Connection(
            h2.config.H2Configuration(client_side=True, header_encoding=None)
        )
        self.connection.initiate_connection()
        self.stream_ids = []
        for _ in range(streams):
            stream_id = self.connection.get_next_available_stream_id()
            request = [(b":method", b"POST"), (b":scheme", b"http"), (b":path", path.encode()),
                       (b":authority", target.encode()), (b"content-type", b"application/grpc"),
                       (b"te", b"trailers")]  # fmt: skip
            request += [(_bytes(k), _bytes(v)) for k, v in headers]
            self.connection.send_headers(stream_id, request)
            if sent:
                prefix = b"\0" + declared.to_bytes(4, "big")
                self.connection.send_data(stream_id, (prefix + b"\0" * sent)[: 5 + sent])
            self.stream_ids.append(stream_id)
        self.stream_id = self.stream_ids[0]
        self.sock.sendall(self.connection.data_to_send())

    def statuses(self, timeout_s: float) -> dict[int, str | None]:
        """Each stream's ending (see `status`) as the server sends them, within timeout_s."""
        import h2.events

        found: dict[int, str | None] = {i: None for i in self.stream_ids}
        deadline = time.monotonic() + timeout_s
        while None in found.values() and time.monotonic() < deadline:
            self.sock.settimeout(max(deadline - time.monotonic(), 0.01))
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                break
            if not data:
                return {i: v or "closed" for i, v in found.items()}
            for event in self.connection.receive_data(data):
                stream = getattr(event, "stream_id", None)
                if stream not in found:
                    continue
                if isinstance(event, h2.events.StreamReset) and found[stream] is None:
                    found[stream] = "reset"  # after trailers, it only ends the upload
                headers = dict(getattr(event, "headers", None) or ())
                if b"grpc-status" in headers:
                    found[stream] = headers[b"grpc-status"].decode()
            pending = self.connection.data_to_send()
            if pending:
                self.sock.sendall(pending)
        return found

    def status(self, timeout_s: float) -> str | None:
        """Wait for the server to end the call: its grpc-status ('4': DEADLINE_EXCEEDED), or
        'reset' / 'closed'; None if nothing came within timeout_s."""
        import h2.events

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.sock.settimeout(max(deadline - time.monotonic(), 0.01))
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return None
            if not data:
                return "closed"
            for event in self.connection.receive_data(data):
                if isinstance(event, h2.events.StreamReset):
                    return "reset"
                headers = getattr(event, "headers", None)
                if headers and event.stream_id == self.stream_id:
                    found = dict(headers)
                    if b"grpc-status" in found:
                        return found[b"grpc-status"].decode()
            pending = self.connection.data_to_send()  # settings and ping acknowledgements
            if pending:
                self.sock.sendall(pending)
        return None

    def close(self) -> None:
        self.sock.close()


def _bytes(value: str | bytes) -> bytes:
    return value.encode() if isinstance(value, str) else value


class IdleConnection:
    """An HTTP/2 connection that opens no call."""

    def __init__(self, target: str) -> None:
        import h2.config
        import h2.connection

        host, port = target.rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=30)
        connection = h2.connection.H2Connection(h2.config.H2Configuration(client_side=True))
        connection.initiate_connection()
        self.sock.sendall(connection.data_to_send())

    def close(self) -> None:
        self.sock.close()


def measure(target: str, seconds: float) -> dict:
    """A normal client's LabelFrame throughput and health latencies over `seconds`."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    from serving.client import pb2_grpc

    requests = sample_requests(store=False)
    stop = threading.Event()
    health_s: list[float] = []
    health_failures: list[str] = []

    def check_health() -> None:
        with grpc.insecure_channel(target) as channel:
            stub = health_pb2_grpc.HealthStub(channel)
            while not stop.is_set():
                start = time.perf_counter()
                try:
                    stub.Check(health_pb2.HealthCheckRequest(), timeout=5)
                    health_s.append(time.perf_counter() - start)
                except grpc.RpcError as error:
                    health_failures.append(error.code().name)
                stop.wait(0.02)

    checker = threading.Thread(target=check_health, daemon=True)
    checker.start()
    done, failures = 0, []
    with grpc.insecure_channel(target) as channel:
        stub = pb2_grpc.AutoLabelerStub(channel)
        start = time.perf_counter()
        while time.perf_counter() - start < seconds:
            try:
                stub.LabelFrame(requests[done % len(requests)], timeout=30)
                done += 1
            except grpc.RpcError as error:
                failures.append(error.code().name)
        elapsed = time.perf_counter() - start
    stop.set()
    checker.join()
    return {
        "frames_per_s": done / elapsed,
        "label_failures": failures,
        "health": percentiles(health_s),
        "health_checks": len(health_s),
        "health_failures": health_failures,
    }


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=10.0, help="length of each phase")
    parser.add_argument("--receive-timeout-s", type=float, default=15.0)
    parser.add_argument("--config", default="configs/tiny.toml")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="service_stall_"))
    repository = prepare_repository(work, args.config)
    server_args = ("--workers", str(args.workers), "--receive-timeout-s",
                   str(args.receive_timeout_s))  # fmt: skip
    with serve(repository, work / "store", *server_args) as server:
        quiet = measure(server.target, args.seconds)
        stalled_started = time.monotonic()
        stalled = [StalledStream(server.target) for _ in range(4 * args.workers)]
        idle = [IdleConnection(server.target) for _ in range(4 * args.workers)]
        loaded = measure(server.target, args.seconds)
        left = args.receive_timeout_s + 10 - (time.monotonic() - stalled_started)
        endings = [s.status(max(left, 1.0)) for s in stalled]
        for connection in stalled + idle:
            connection.close()
    result = {"workers": args.workers, "stalled_streams": len(stalled),
              "idle_connections": len(idle), "quiet": quiet, "stalled": loaded,
              "throughput_ratio": loaded["frames_per_s"] / quiet["frames_per_s"],
              "stalled_stream_endings": endings,
              "receive_timeout_s": args.receive_timeout_s}  # fmt: skip
    print(f"--workers {args.workers}: {len(stalled)} stalled streams + {len(idle)} idle "
          f"connections, {args.seconds:.0f} s per phase, model {args.config}")  # fmt: skip
    print("\n| phase | LabelFrame frames/s | failed calls | health checks | health p50 ms | "
          "p99 ms | max ms | failed health checks |")  # fmt: skip
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name, figures in (("quiet", quiet), ("stalled + idle open", loaded)):
        h = figures["health"]
        print(f"| {name} | {figures['frames_per_s']:.1f} | {len(figures['label_failures'])} | "
              f"{figures['health_checks']} | {h['p50_ms']:.1f} | {h['p99_ms']:.1f} | "
              f"{h['max_ms']:.1f} | {len(figures['health_failures'])} |")  # fmt: skip
    print(f"\nthroughput with the stalled streams open / without: {result['throughput_ratio']:.2f}")
    counts = {e: endings.count(e) for e in set(endings)}
    print(f"stalled streams' endings after the {args.receive_timeout_s:.0f} s receive timeout "
          f"(grpc-status 4 = DEADLINE_EXCEEDED): {counts}")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    argv = ["--workers", str(args.workers), "--seconds", str(args.seconds), "--config",
            args.config, "--receive-timeout-s", str(args.receive_timeout_s)]  # fmt: skip
    print(f"\nrerun: {rerun('service_stall', argv)}")


if __name__ == "__main__":
    main()
