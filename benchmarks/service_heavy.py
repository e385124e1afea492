"""Heavy and stalled clients against `detmatch serve` (a subprocess, port 0), seen from outside:
its own gRPC stubs and raw HTTP/2 (the `h2` library).

    python -m benchmarks.service_heavy [--stalled 70] [--heavy 16] [--points 3900000]

Phase 1, stalled: an honest client's LabelFrame (store off) and GetModelInfo latencies on an
otherwise idle server, then again with --stalled authenticated streams open (headers and the
first 100 bytes of a 1 MB message, then nothing; 14 per connection). Target: every honest
call OK, p99 within 2x of the idle server's.
Phase 2, heavy: --heavy clients at once, each sending one frame of --points LiDAR points
(3.9 M points: 62 MB, under the 64 MiB message cap of the server before 2026-12-07) and the
KITTI image; the server's peak RSS (VmHWM) and what each call got, then whether a normal
frame is served afterwards. Target at the default settings: peak RSS <= 1.5 GB, no INTERNAL.
`--serve-arg` passes flags to the server (for example `--serve-arg=--max-message-mb=64` and
`--serve-arg=--max-points=4000000` to send the frames through the byte budget).
"""

from __future__ import annotations

import json
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import grpc
import numpy as np

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import percentiles, prepare_repository, sample_requests, serve
from benchmarks.service_stall import StalledStream

TOKEN = "bench-token"
PER_CONNECTION = 14


def peak_rss_mib(pid: int) -> float:
    """The process's peak resident set so far (VmHWM), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def honest_calls(target: str, calls: int) -> dict:
    """`calls` LabelFrame (store off) and GetModelInfo calls in turn: latencies and failures."""
    from serving.client import pb2, pb2_grpc

    requests = sample_requests(store=False)
    metadata = (("authorization", f"Bearer {TOKEN}"),)
    label_s, info_s, failures = [], [], []
    with grpc.insecure_channel(target, options=[("grpc.max_send_message_length", 2**26)]) as ch:
        stub = pb2_grpc.AutoLabelerStub(ch)
        for i in range(calls):
            for method, request, times in (
                (stub.LabelFrame, requests[i % len(requests)], label_s),
                (stub.GetModelInfo, pb2.GetModelInfoRequest(), info_s),
            ):
                start = time.perf_counter()
                try:
                    method(request, timeout=60, metadata=metadata)
                    times.append(time.perf_counter() - start)
                except grpc.RpcError as error:
                    failures.append(error.code().name)
    return {"label": percentiles(label_s), "model_info": percentiles(info_s),
            "ok": len(label_s) + len(info_s), "failures": failures}  # fmt: skip


def heavy_request(points: int):
    """A KITTI sample frame's request with `points` LiDAR points (random, in range)."""
    from serving.decode import encode_points

    request = sample_requests(store=False)[0]
    rng = np.random.default_rng(0)
    cloud = rng.uniform([0, -30, -2, 0], [60, 30, 1, 1], size=(points, 4)).astype(np.float32)
    request.points = encode_points(cloud)
    request.frame_id = "heavy"
    return request


def heavy_calls(target: str, clients: int, points: int) -> dict[str, int]:
    """`clients` channels each sending one heavy frame at once: status codes counted."""
    from serving.client import pb2_grpc

    request = heavy_request(points)
    metadata = (("authorization", f"Bearer {TOKEN}"),)
    options = [("grpc.max_send_message_length", 2**26)]

    def one(_: int) -> str:
        with grpc.insecure_channel(target, options=options) as channel:
            try:
                pb2_grpc.AutoLabelerStub(channel).LabelFrame(
                    request, timeout=300, metadata=metadata
                )
                return "OK"
            except grpc.RpcError as error:
                return error.code().name

    with ThreadPoolExecutor(clients) as pool:
        codes = list(pool.map(one, range(clients)))
    return {code: codes.count(code) for code in sorted(set(codes))}


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--stalled", type=int, default=70)
    parser.add_argument("--calls", type=int, default=20, help="honest calls per phase")
    parser.add_argument("--heavy", type=int, default=16)
    parser.add_argument("--points", type=int, default=3_900_000)
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--serve-arg", action="append", default=[], help="flag for the server")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="service_heavy_"))
    repository = prepare_repository(work, args.config)
    server_args = ("--workers", "2", "--receive-timeout-s", "120", *args.serve_arg)
    env = {"DETMATCH_TOKEN": TOKEN}
    result: dict = {"config": args.config, "serve_args": list(server_args)}
    with serve(repository, work / "store", *server_args, env=env) as server:
        honest_calls(server.target, 3)  # warm-up
        result["idle"] = honest_calls(server.target, args.calls)
        auth = [("authorization", f"Bearer {TOKEN}")]
        stalled = []
        for start in range(0, args.stalled, PER_CONNECTION):
            count = min(PER_CONNECTION, args.stalled - start)
            stalled.append(StalledStream(server.target, streams=count, headers=auth))
        result["stalled"] = honest_calls(server.target, args.calls)
        for connection in stalled:
            connection.close()
        idle_p99 = result["idle"]["label"]["p99_ms"]
        result["stalled_p99_ratio"] = result["stalled"]["label"]["p99_ms"] / idle_p99
        before = peak_rss_mib(server.pid)
        started = time.perf_counter()
        result["heavy_codes"] = heavy_calls(server.target, args.heavy, args.points)
        result["heavy_wall_s"] = time.perf_counter() - started
        result["rss_before_heavy_mib"] = before
        result["peak_rss_mib"] = peak_rss_mib(server.pid)
        result["after_heavy"] = honest_calls(server.target, 3)
    log = server.log()
    result["log_errors"] = log.count('"level": "ERROR"')
    result["log_tracebacks"] = log.count("Traceback")
    heavy_mb = len(heavy_request(args.points).SerializeToString()) / 1e6
    print(f"model {args.config}; server flags {' '.join(server_args)}")
    print(
        "\n| phase | honest calls OK | failed | LabelFrame p50 ms | p99 ms | GetModelInfo p99 ms |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for name in ("idle", "stalled"):
        r = result[name]
        label = "idle" if name == "idle" else f"{args.stalled} stalled streams open"
        print(f"| {label} | {r['ok']} | {len(r['failures'])} | {r['label']['p50_ms']:.1f} | "
              f"{r['label']['p99_ms']:.1f} | {r['model_info']['p99_ms']:.1f} |")  # fmt: skip
    print(f"\nLabelFrame p99 with the stalled streams / idle: {result['stalled_p99_ratio']:.2f}")
    print(f"\n{args.heavy} concurrent {heavy_mb:.0f} MB frames ({args.points} points): "
          f"{result['heavy_codes']} in {result['heavy_wall_s']:.1f} s; server peak RSS "
          f"{result['peak_rss_mib']:.0f} MiB (before: {before:.0f} MiB); afterwards "
          f"{result['after_heavy']['ok']} of 6 honest calls OK")  # fmt: skip
    print(f"server log: {result['log_errors']} ERROR lines, {result['log_tracebacks']} tracebacks")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nrerun: {rerun('service_heavy')}")


if __name__ == "__main__":
    main()
