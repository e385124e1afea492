"""SIGKILL under load: `detmatch serve` is killed again and again while clients store frames;
no acknowledged frame may be lost or altered, and the restarts leave no debris.

    python -m benchmarks.service_sigkill [--kills 20] [--clients 3] [--config configs/tiny.toml]

Each round starts the server on the same store, lets --clients threads label and store new
frames (the KITTI sample frames under fresh ids) for a random 0.4-1.2 s, and kills it with
SIGKILL mid-flight. A frame counts as acknowledged when its call returned OK. After the last
kill the server is started once more (its recovery runs) and stopped with SIGTERM. Figures:
acknowledged frames, those missing from the store (target 0), those whose stored image or
points differ from what was sent (target 0), `check_integrity` problems (target 0), files in
the shard that no index row lists after the final restart (target 0: no debris), and what
the restarts' recovery removed or finished (temporary files, committed files still under
their temporary names, files of frames killed before their commit), summed from their log
lines.
"""

from __future__ import annotations

import hashlib
import json
import random
import tempfile
import threading
import time
from pathlib import Path

import grpc

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import prepare_repository, sample_requests, serve


def label_until(target: str, stop: threading.Event, worker: int, round_: int, acked: dict):
    from serving.client import pb2_grpc

    requests = sample_requests()
    with grpc.insecure_channel(target, options=[("grpc.max_send_message_length", 64 << 20)]) as ch:
        stub = pb2_grpc.AutoLabelerStub(ch)
        i = 0
        while not stop.is_set():
            source = i % len(requests)
            request = requests[source]
            request.frame_id = f"k{round_:03d}_w{worker}_{i:05d}"
            try:
                response = stub.LabelFrame(request, timeout=30)
            except grpc.RpcError:
                return  # the server is gone
            if response.stored:
                acked[request.frame_id] = (source, response.model_version)
            i += 1


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--clients", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--config", default="configs/tiny.toml")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    from serving.store import check_integrity, list_frames

    rng = random.Random(args.seed)
    work = Path(args.work or tempfile.mkdtemp(prefix="service_sigkill_"))
    repository = prepare_repository(work, args.config)
    store = work / f"store_sigkill_{time.strftime('%Y%m%d-%H%M%S')}"
    acked: dict[str, tuple[int, str]] = {}
    started = time.perf_counter()
    for round_ in range(args.kills):
        with serve(repository, store) as server:
            stop = threading.Event()
            threads = [threading.Thread(target=label_until,
                                        args=(server.target, stop, w, round_, acked))
                       for w in range(args.clients)]  # fmt: skip
            for thread in threads:
                thread.start()
            time.sleep(rng.uniform(0.4, 1.2))
            server.process.kill()  # SIGKILL, calls in flight
            server.process.wait(timeout=30)
            stop.set()
            for thread in threads:
                thread.join(timeout=60)
    with serve(repository, store) as server:  # the final restart: recovery, then SIGTERM
        pass
    elapsed = time.perf_counter() - started
    log = server.log()
    sent = sample_requests()
    image_sha = [hashlib.sha256(r.image).hexdigest() for r in sent]
    points_sha = [hashlib.sha256(r.points).hexdigest() for r in sent]
    records = {r.frame_id: r for r in list_frames(store)}
    missing = [k for k in acked if k not in records]
    altered = []
    for frame_id, (source, version) in acked.items():
        record = records.get(frame_id)
        if record is None:
            continue
        files = {Path(k).parent.name: v for k, v in record.files.items()}
        if (files["image_2"], files["velodyne"], record.model_version) != (
            image_sha[source], points_sha[source], version
        ):  # fmt: skip
            altered.append(frame_id)
    problems = check_integrity(store)
    listed = {f"shards/{r.shard}/{rel}" for r in records.values() for rel in r.files}
    on_disk = {p.relative_to(store).as_posix() for p in store.rglob("*")
               if p.is_file() and "index.sqlite" not in p.name and p.name != ".lock"}  # fmt: skip
    debris = sorted(on_disk - listed)
    opened = [json.loads(line) for line in log.splitlines() if '"label store opened"' in line]
    recovered = {key: sum(o[key] for o in opened)
                 for key in ("temporary_removed", "rolled_forward", "orphans_removed")}  # fmt: skip
    print(f"{args.kills} SIGKILLs under load ({args.clients} clients), then one restart; "
          f"{elapsed:.0f} s in all, model {args.config}")  # fmt: skip
    print("\n| figure | value |\n| --- | ---: |")
    for name, value in (
        ("acknowledged frames", len(acked)),
        ("frames in the store", len(records)),
        ("acknowledged frames missing (target 0)", len(missing)),
        ("acknowledged frames altered (target 0)", len(altered)),
        ("integrity problems (target 0)", len(problems)),
        ("files no row lists after the restart (target 0)", len(debris)),
        ("temporary files removed by the restarts", recovered["temporary_removed"]),
        ("committed files renamed into place (rolled forward)", recovered["rolled_forward"]),
        ("files of uncommitted frames removed", recovered["orphans_removed"]),
    ):
        print(f"| {name} | {value} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"acked": len(acked), "missing": missing,
            "altered": altered, "problems": problems, "debris": debris,
            "recovered": recovered}, indent=2) + "\n")  # fmt: skip
    argv = ["--kills", str(args.kills), "--clients", str(args.clients), "--seed",
            str(args.seed), "--config", args.config]  # fmt: skip
    print(f"\nrerun: {rerun('service_sigkill', argv)}")


if __name__ == "__main__":
    main()
