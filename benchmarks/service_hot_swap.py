"""Hot swap under load, with broken versions in the sequence: no call may fail, and a broken
version must never serve.

    python -m benchmarks.service_hot_swap [--clients 2] [--interval-s 2] [--config ...]

While --clients threads label continuously (store on), versions are published and promoted
one after another every --interval-s seconds: good copies of version 000001, a version whose
3D graph is truncated after its promotion (a failing disk), and a hand-copied folder whose
manifest names another version (marker written by hand). The server polls every 0.2 s.
Figures: calls and failed calls (target 0), the versions that answered (target: every good
one, never a broken one), the server's log lines about the broken ones (each once), and the
time from a good version's promotion to the first answer it gave.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import grpc

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import percentiles, prepare_repository, sample_requests, serve

SEQUENCE = ("good", "corrupt", "good", "hand-copied", "good", "corrupt", "good")


def publish(repository: Path, version: str, kind: str) -> None:
    """A copy of 000001 as `version`: promoted (good), promoted then truncated (corrupt), or a
    folder copied as it is with a marker (hand-copied: its manifest names 000001)."""
    from serving.repository import promote

    target = repository / version
    staging = repository / f".staging-bench-{version}"
    shutil.copytree(repository / "000001", staging)
    (staging / "PROMOTED").unlink(missing_ok=True)
    if kind != "hand-copied":
        manifest = json.loads((staging / "manifest.json").read_text())
        manifest["version"] = version
        (staging / "manifest.json").write_text(json.dumps(manifest))
    staging.rename(target)
    if kind == "hand-copied":
        (target / "PROMOTED").write_text('{"promoted_at": "by hand"}\n')
        return
    promote(repository, version)
    if kind == "corrupt":
        model = target / "detector3d.onnx"
        model.write_bytes(model.read_bytes()[:100])


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--clients", type=int, default=2)
    parser.add_argument("--interval-s", type=float, default=2.0)
    parser.add_argument("--config", default="configs/tiny.toml")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    from serving.client import pb2_grpc

    work = Path(args.work or tempfile.mkdtemp(prefix="service_hot_swap_"))
    source = prepare_repository(work, args.config)
    run = time.strftime("%Y%m%d-%H%M%S")
    repository = work / f"swap_repository_{run}"
    shutil.copytree(source / "000001", repository / "000001")
    answers: list[tuple[float, str]] = []
    failures: list[str] = []
    lock = threading.Lock()
    stop = threading.Event()
    promoted_at: dict[str, float] = {}
    kinds: dict[str, str] = {}

    def client(number: int, target: str) -> None:
        requests = sample_requests(prefix=f"h{number}_")
        with grpc.insecure_channel(
            target, options=[("grpc.max_send_message_length", 64 << 20)]
        ) as ch:
            stub = pb2_grpc.AutoLabelerStub(ch)
            i = 0
            while not stop.is_set():
                request = requests[i % len(requests)]
                request.frame_id = f"h{number}_{i:06d}"
                try:
                    response = stub.LabelFrame(request, timeout=60)
                    with lock:
                        answers.append((time.monotonic(), response.model_version))
                except grpc.RpcError as error:
                    with lock:
                        failures.append(error.code().name)
                i += 1

    with serve(repository, work / f"store_swap_{run}", "--poll-s", "0.2") as server:
        threads = [threading.Thread(target=client, args=(n, server.target))
                   for n in range(args.clients)]  # fmt: skip
        for thread in threads:
            thread.start()
        time.sleep(args.interval_s)
        for number, kind in enumerate(SEQUENCE, start=2):
            version = f"{number:06d}"
            publish(repository, version, kind)
            promoted_at[version], kinds[version] = time.monotonic(), kind
            time.sleep(args.interval_s)
        stop.set()
        for thread in threads:
            thread.join(timeout=120)
    log = server.log()
    served = Counter(v for _, v in answers)
    first = {}
    for at, version in answers:
        first.setdefault(version, at)
    delays = [first[v] - promoted_at[v] for v in promoted_at if v in first]
    good = [v for v, k in kinds.items() if k == "good"]
    broken = [v for v, k in kinds.items() if k != "good"]
    print(f"{len(SEQUENCE)} versions published every {args.interval_s:.1f} s under load "
          f"({args.clients} clients, store on), model {args.config}")  # fmt: skip
    print("\n| version | kind | answers |\n| --- | --- | ---: |")
    for version in ["000001", *kinds]:
        print(f"| {version} | {kinds.get(version, 'initial')} | {served.get(version, 0)} |")
    failed_lines = {v: log.count(f"loading model version {v} failed") for v in broken}
    print(f"\ncalls: {len(answers) + len(failures)}, failed: {len(failures)} (target 0)")
    print(f"good versions that served: {sum(v in served for v in good)} of {len(good)}; broken "
          f"versions that served: {sum(v in served for v in broken)} (target 0)")  # fmt: skip
    print(f"'loading ... failed' log lines per broken version (target 1 each): {failed_lines}")
    delay = percentiles(delays)
    print(f"promotion -> first answer of a good version: p50 {delay['p50_ms']:.0f} ms, max "
          f"{delay['max_ms']:.0f} ms (a 200 ms poll, then load, verify, warm up)")  # fmt: skip
    if args.json:
        figures = {"served": served, "failures": failures, "kinds": kinds, "delays_s": delays,
                   "failed_lines": failed_lines}  # fmt: skip
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")
    argv = ["--clients", str(args.clients), "--interval-s", str(args.interval_s),
            "--config", args.config]  # fmt: skip
    print(f"\nrerun: {rerun('service_hot_swap', argv)}")


if __name__ == "__main__":
    main()
