"""Load on `detmatch serve`: throughput, latency percentiles, errors and memory at 1/2/4/8
clients, with the label store on and off (or dynamic batching off and on), measured in one run.

    python -m benchmarks.service_load [--clients 1 2 4 8] [--seconds 10] [--workers 2]
                                      [--compare batching --max-batch-size 4]
                                      [--config configs/synth_cpu.toml] [--raw-image] [--int8]

Two servers run side by side, one storing every frame (each request a new frame id, so
every call writes a frame: files, fsyncs, the index) and one with `store: false`; for each
client count the two are measured in alternating rounds (--rounds), so both see the same
machine. Clients
are threads of this process sending the three KITTI sample frames (full resolution, 0.7-0.9 MB
PNG and 1.8-2.0 MB of points) one call after another. Figures: frames/s, p50/p95/p99
latency, failed calls (target 0), the server's RSS at the start, its peak and at the end
(sampled every 0.5 s), the store-on / store-off throughput ratio (target at 4 clients: >=
0.8), and the store's group commit: frames per committed batch (from the server's log).
--raw-image: the clients send the frames' pixels uncompressed (raw_image) instead of PNG;
--int8: the servers serve an INT8 version of the model (`--quantize int8`); --checkpoint: the
model is this trained checkpoint instead of --config with random weights (INT8 kernels gain
little on random weights: BENCHMARKS.md).
"""

from __future__ import annotations

import contextlib
import json
import tempfile
import threading
import time
from pathlib import Path

import grpc

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import (
    RssSampler,
    cpu_seconds,
    int8_repository,
    percentiles,
    prepare_repository,
    sample_requests,
    serve,
)


def run_clients(
    target: str, clients: int, seconds: float, store: bool, tag: str, raw_image: bool = False
) -> dict:
    """`clients` threads labeling for `seconds`; each call a new frame id when storing;
    raw_image: the pixels sent uncompressed."""
    from serving.client import pb2_grpc

    latencies: list[float] = []
    failures: list[str] = []
    lock = threading.Lock()
    start_line = threading.Barrier(clients + 1)
    deadline = [0.0]

    def client(number: int) -> None:
        requests = sample_requests(store=store, raw_image=raw_image)
        with grpc.insecure_channel(target, options=[
            ("grpc.max_send_message_length", 64 << 20)]) as channel:  # fmt: skip
            stub = pb2_grpc.AutoLabelerStub(channel)
            stub.GetModelInfo.future  # noqa: B018 - the channel connects on the first call
            start_line.wait()
            i = 0
            while time.perf_counter() < deadline[0]:
                request = requests[i % len(requests)]
                request.frame_id = f"{tag}c{number}_{i:06d}"
                started = time.perf_counter()
                try:
                    stub.LabelFrame(request, timeout=60)
                    with lock:
                        latencies.append(time.perf_counter() - started)
                except grpc.RpcError as error:
                    with lock:
                        failures.append(error.code().name)
                i += 1

    threads = [threading.Thread(target=client, args=(n,)) for n in range(clients)]
    for thread in threads:
        thread.start()
    deadline[0] = time.perf_counter() + seconds
    began = time.perf_counter()
    start_line.wait()
    for thread in threads:
        thread.join()
    elapsed = time.perf_counter() - began
    return {"clients": clients, "seconds": elapsed, "latencies": latencies,
            "failed": failures}  # fmt: skip


def merge(parts: list[dict]) -> dict:
    """One row from the rounds of one client count and mode."""
    latencies = [x for p in parts for x in p["latencies"]]
    calls = len(latencies)
    return {
        "clients": parts[0]["clients"],
        "frames_per_s": calls / sum(p["seconds"] for p in parts),
        "calls": calls,
        "failed": [x for p in parts for x in p["failed"]],
        "server_cpu_ms_per_frame": 1000 * sum(p["cpu_s"] for p in parts) / max(calls, 1),
        **percentiles(latencies),
    }


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--clients", nargs="+", type=int, default=[1, 2, 4, 8])
    parser.add_argument("--seconds", type=float, default=12.0, help="per client count and mode")
    parser.add_argument(
        "--rounds", type=int, default=3, help="rounds the seconds are split in, modes alternating"
    )
    parser.add_argument("--workers", type=int, default=4, help="the server's (its default)")
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--threads", type=int, default=0,
                        help="the server's onnxruntime threads (0: its default)")  # fmt: skip
    parser.add_argument("--checkpoint", help="serve this trained checkpoint (its own config) "
                        "instead of --config with random weights")  # fmt: skip
    parser.add_argument("--raw-image", action="store_true", help="clients send raw pixels")
    parser.add_argument("--int8", action="store_true", help="serve an INT8 version")
    parser.add_argument("--compare", choices=("store", "batching"), default="store",
                        help="the two servers: the store off and on, or both storing with "
                        "dynamic batching off and on")  # fmt: skip
    parser.add_argument("--max-batch-size", type=int, default=4,
                        help="the batching server's (--compare batching)")  # fmt: skip
    parser.add_argument("--max-queue-delay-us", type=int, default=2000,
                        help="the batching server's (--compare batching)")  # fmt: skip
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="service_load_"))
    repository = prepare_repository(work, args.config, args.checkpoint)
    if args.int8:
        repository = int8_repository(work, repository)
    server_args = ("--workers", str(args.workers), "--threads", str(args.threads))
    batching = ("--max-batch-size", str(args.max_batch_size),
                "--max-queue-delay-us", str(args.max_queue_delay_us))  # fmt: skip
    # Two servers, measured in alternating rounds: (mode, whether its calls store, its flags);
    # the first is the baseline of the ratio.
    if args.compare == "store":
        modes = [("off", False, server_args), ("on", True, server_args)]
    else:
        modes = [("single", True, server_args), ("batched", True, server_args + batching)]
    rows = []
    run = time.strftime("%Y%m%d-%H%M%S")  # a fresh store: every stored call creates a frame
    with contextlib.ExitStack() as stack:
        servers = {mode: stack.enter_context(serve(repository, work / f"store_{mode}_{run}",
                                                   *flags))
                   for mode, _, flags in modes}  # fmt: skip
        stores = {mode: stores for mode, stores, _ in modes}
        samplers = {mode: stack.enter_context(RssSampler(server.pid))
                    for mode, server in servers.items()}  # fmt: skip
        for mode, server in servers.items():  # warm up: first calls
            run_clients(server.target, 1, 2.0, stores[mode], "warm", args.raw_image)
        for clients in args.clients:
            parts: dict[str, list] = {mode: [] for mode in servers}
            rss_before = {mode: server.rss_mib() for mode, server in servers.items()}
            for round_ in range(args.rounds):  # interleaved: both modes see the same machine
                for mode, server in servers.items():
                    cpu_before = cpu_seconds(server.pid)
                    figures = run_clients(server.target, clients, args.seconds / args.rounds,
                                          stores[mode], f"n{clients}r{round_}",
                                          args.raw_image)  # fmt: skip
                    figures["cpu_s"] = cpu_seconds(server.pid) - cpu_before
                    parts[mode].append(figures)
            for mode, server in servers.items():
                rows.append({"mode": mode, **merge(parts[mode]),
                             "rss_before_mib": rss_before[mode],
                             "rss_after_mib": server.rss_mib()})  # fmt: skip
    log = servers[modes[-1][0]].log()  # the store's commit counts are logged when it closes
    model = args.checkpoint or args.config
    print(f"model {model}{' (INT8)' if args.int8 else ''}, --workers {args.workers} "
          f"--threads {args.threads}, "
          f"{args.seconds:.0f} s per row; clients send the 3 KITTI sample frames "
          f"({'raw pixels' if args.raw_image else 'PNG'})")  # fmt: skip
    if args.compare == "batching":
        print(f"both servers store every frame; 'batched': {' '.join(batching)}")
    column = "store" if args.compare == "store" else "batching"
    print(f"\n| {column} | clients | frames/s | p50 ms | p95 ms | p99 ms | failed | server CPU ms "
          "per frame | RSS MiB before / after |")  # fmt: skip
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for row in rows:
        print(f"| {row['mode']} | {row['clients']} | {row['frames_per_s']:.1f} | "
              f"{row['p50_ms']:.0f} | {row['p95_ms']:.0f} | {row['p99_ms']:.0f} | "
              f"{len(row['failed'])} | {row['server_cpu_ms_per_frame']:.1f} | "
              f"{row['rss_before_mib']:.0f} / {row['rss_after_mib']:.0f} |")  # fmt: skip
    (base, _, _), (other, _, _) = modes
    print(f"\n| clients | {column} {other} / {base} throughput |")
    print("| ---: | ---: |")
    ratios = {}
    for clients in args.clients:
        first, second = (next(r for r in rows if r["clients"] == clients and r["mode"] == m)
                         for m in (base, other))  # fmt: skip
        ratios[clients] = second["frames_per_s"] / first["frames_per_s"]
        print(f"| {clients} | {ratios[clients]:.2f} |")
    for mode, sampler in samplers.items():
        samples = sampler.samples
        print(f"RSS of the {mode} server over the run: first {samples[0][1]:.0f} MiB, "
              f"peak {sampler.peak:.0f} MiB, last {samples[-1][1]:.0f} MiB "
              f"({len(samples)} samples over {samples[-1][0]:.0f} s)")  # fmt: skip
    closed = [json.loads(line) for line in log.splitlines() if '"label store closed"' in line]
    if closed:
        frames, batches = closed[-1]["frames_committed"], closed[-1]["commits"]
        print(
            f"group commit: {frames} frames written in {batches} commits "
            f"({frames / max(batches, 1):.2f} frames per commit)"
        )
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "ratios": ratios,
            "rss": {m: s.samples for m, s in samplers.items()}}, indent=2) + "\n")  # fmt: skip
    argv = ["--clients", *map(str, args.clients), "--seconds", str(args.seconds), "--rounds",
            str(args.rounds), "--workers", str(args.workers), "--threads", str(args.threads),
            "--config", args.config,
            *(["--checkpoint", args.checkpoint] if args.checkpoint else []),
            *(["--raw-image"] if args.raw_image else []),
            *(["--int8"] if args.int8 else []),
            *(["--compare", "batching", "--max-batch-size",
               str(args.max_batch_size), "--max-queue-delay-us", str(args.max_queue_delay_us)]
              if args.compare == "batching" else [])]  # fmt: skip
    print(f"\nrerun: {rerun('service_load', argv)}")


if __name__ == "__main__":
    main()
