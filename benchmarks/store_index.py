"""The shared label store's cost: LabelFrame throughput of `detmatch serve` storing every frame
with the embedded index (SQLite, one per shard) against the shared one (PostgreSQL), at the
same client counts, measured in one run.

    python -m benchmarks.store_index [--clients 4] [--seconds 12] [--postgres URL]

Two servers run side by side on one model, each storing every frame (each request a new
frame id): one with `--store DIR`, one with `--store postgresql://... --store-root DIR`. For
each client count the two are measured in alternating rounds, so both see the same machine.
Without --postgres a throwaway server is started with `.ci/postgres` (PostgreSQL's binaries
must be installed). Figures: frames/s, p50 / p99 latency and failed calls per index, and the
PostgreSQL / SQLite throughput ratio, and
the server's CPU per frame (the PostgreSQL server's own CPU is not counted).
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import REPO, cpu_seconds, prepare_repository, serve
from benchmarks.service_load import merge, run_clients


@contextmanager
def postgres(url: str | None):
    """The given server's URL, or a throwaway server's."""
    if url:
        yield url
        return
    directory = Path(tempfile.mkdtemp(prefix="detmatch-postgres-"))
    directory.chmod(0o755)  # the server runs as the postgres user
    script = str(REPO / ".ci" / "postgres")
    started = subprocess.run([script, "start", str(directory)], capture_output=True, text=True)
    if started.returncode != 0:
        raise SystemExit(f"cannot start PostgreSQL: {started.stderr.strip()}")
    try:
        yield started.stdout.strip()
    finally:
        subprocess.run([script, "stop", str(directory)])


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--clients", nargs="+", type=int, default=[4])
    parser.add_argument("--seconds", type=float, default=12.0, help="per client count and index")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, the indexes alternating")
    parser.add_argument("--workers", type=int, default=4, help="the servers' (their default)")
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--postgres", help="a PostgreSQL URL (default: a throwaway server)")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="store_index_"))
    repository = prepare_repository(work, args.config)
    run = time.strftime("%Y%m%d-%H%M%S")  # fresh stores: every call creates a frame
    rows = []
    with postgres(args.postgres) as url:
        shared_root = work / f"shared_{run}"
        with (
            serve(repository, work / f"sqlite_{run}", "--workers", str(args.workers)) as sqlite,
            serve(repository, shared_root, "--workers", str(args.workers), "--store", url,
                  "--store-root", str(shared_root)) as shared,
        ):  # fmt: skip
            servers = {"SQLite": sqlite, "PostgreSQL": shared}
            for server in servers.values():  # warm up: first calls
                run_clients(server.target, 1, 2.0, True, "warm")
            for clients in args.clients:
                parts: dict[str, list] = {name: [] for name in servers}
                for round_ in range(args.rounds):
                    for name, server in servers.items():
                        cpu_before = cpu_seconds(server.pid)
                        figures = run_clients(server.target, clients, args.seconds / args.rounds,
                                              True, f"n{clients}r{round_}")  # fmt: skip
                        figures["cpu_s"] = cpu_seconds(server.pid) - cpu_before
                        parts[name].append(figures)
                rows += [{"index": name, **merge(parts[name])} for name in servers]
    print(f"model {args.config}, --workers {args.workers}, {args.seconds:.0f} s per row, every "
          "frame stored; clients send the 3 KITTI sample frames")  # fmt: skip
    print("\n| index | clients | frames/s | p50 ms | p99 ms | failed | server CPU ms per frame |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for row in rows:
        print(f"| {row['index']} | {row['clients']} | {row['frames_per_s']:.1f} | "
              f"{row['p50_ms']:.0f} | {row['p99_ms']:.0f} | {len(row['failed'])} | "
              f"{row['server_cpu_ms_per_frame']:.1f} |")  # fmt: skip
    print("\n| clients | PostgreSQL / SQLite throughput |")
    print("| ---: | ---: |")
    ratios = {}
    for clients in args.clients:
        by_index = {r["index"]: r for r in rows if r["clients"] == clients}
        ratios[clients] = (
            by_index["PostgreSQL"]["frames_per_s"] / by_index["SQLite"]["frames_per_s"]
        )
        print(f"| {clients} | {ratios[clients]:.2f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "ratios": ratios}, indent=2) + "\n")
    argv = ["--clients", *map(str, args.clients), "--seconds", str(args.seconds), "--rounds",
            str(args.rounds), "--workers", str(args.workers), "--config", args.config]  # fmt: skip
    print(f"\nrerun: {rerun('store_index', argv)}")


if __name__ == "__main__":
    main()
