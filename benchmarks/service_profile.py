"""Where a loaded server's CPU goes per LabelFrame call, store on and off: `py-spy` samples
`detmatch serve` (a subprocess) while one client sends the three KITTI sample frames (full
resolution) one call after another, as PNG files and as raw pixels (raw_image).

    python -m benchmarks.service_profile [--seconds 20] [--config configs/synth_cpu.toml]
        [--images png raw]

Every sampled stack of an active server thread (threads waiting on a queue, a condition,
epoll or the disk are left out) is put in the first stage (in the order of STAGES) whose marker its
frames hold; a stage's milliseconds per frame are its share of the samples times the
server's CPU time per frame (/proc: user + system), so time spent waiting for a core that
another process holds does not count. "graphs" (the 2D and 3D onnxruntime runs) is what the
models themselves cost; the rest is the request handling the issue-42 targets want close to
them (server CPU / graphs <= 1.3 store off, <= 1.5 store on). Needs py-spy (`pip install
py-spy`; ptrace permission: root, or CAP_SYS_PTRACE in a container).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import grpc

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import cpu_seconds, prepare_repository, sample_requests, serve

# (stage, markers): a stack belongs to the first stage one of whose markers it holds.
STAGES = (
    ("graph 2D", ("detect_2d",), ("onnxruntime",)),
    ("graph 3D", ("detect_3d",), ("onnxruntime",)),
    ("pillarize", ("pillarize",), ()),
    ("2D/3D outputs and inputs", ("detect_2d", "detect_3d"), ()),
    ("matching", ("match_detections",), ()),
    ("image decode", ("decode_image", "decode_raw_image"), ()),
    ("points decode", ("decode_points",), ()),
    ("calibration and ids", ("decode_calibration", "decode_frame_id", "decode_namespace"), ()),
    ("proto -> request", ("frame_request",), ()),
    ("store", ("put (serving/store", "store_labels"), ()),
    ("response", ("_response",), ()),
    ("request parse (edge)", ("_parse (serving/edge",), ()),
    ("metrics and logs", ("observe", "serving/logs", "prometheus"), ()),
    ("labeler other", ("label (serving/labeler",), ()),
)
GRAPHS = ("graph 2D", "graph 3D")
# Leaf frames of threads that wait (py-spy does not always see a blocked thread as idle).
IDLE_LEAVES = ("_worker (concurrent/futures/thread.py", "EpollSelector.select", "Condition.wait",
               "Event.wait", "LabelStore._commit_loop (serving/store.py",
               "Thread.run (threading.py", "Thread._bootstrap_inner")  # fmt: skip
# Leaf frames of the store's threads waiting on the disk: an fsync, the renames after it and
# SQLite's commit (its own fsync) put the thread in uninterruptible sleep, which py-spy samples
# as active. They wait, they do not compute: counted as CPU they would take a share of the
# server's CPU time that the disk, not the processor, spent.
DISK_WAIT_LEAVES = ("fsync_path (detmatch/files.py", "LabelStore._commit_batch (serving/store.py",
                    "transaction (serving/store_layout.py")  # fmt: skip


def stage_of(stack: str) -> str | None:
    """The stage of one sampled stack (frames root first, ';'-joined); None for a wait."""
    if stack.rsplit(";", 1)[-1].startswith(IDLE_LEAVES + DISK_WAIT_LEAVES):
        return None
    for name, markers, also in STAGES:
        if any(m in stack for m in markers) and all(a in stack for a in also):
            return name
    return "gRPC, event loop, other"


def profile(
    target: str, pid: int, seconds: float, store: bool, rate: int, out: Path, image: str = "png"
) -> dict:
    """Record the server while one client labels frames (image: "png", the files as they
    are, or "raw", their pixels uncompressed); the per-stage figures."""
    from serving.client import pb2_grpc

    requests = sample_requests(store=store, prefix="p" if store else "", raw_image=image == "raw")
    frames, stop = [0], threading.Event()

    def client() -> None:
        with grpc.insecure_channel(target) as channel:
            stub = pb2_grpc.AutoLabelerStub(channel)
            i = 0
            while not stop.is_set():
                request = requests[i % len(requests)]
                if store:
                    request.frame_id = f"p{i:06d}"  # a new frame each call: every call writes
                stub.LabelFrame(request, timeout=60)
                frames[0] += 1
                i += 1

    thread = threading.Thread(target=client)
    thread.start()
    time.sleep(1.0)  # past the first calls
    counted, cpu = frames[0], cpu_seconds(pid)
    subprocess.run(
        ["py-spy", "record", "--pid", str(pid), "--duration", str(int(seconds)), "--rate",
         str(rate), "--format", "raw", "--output", str(out)],
        check=True, capture_output=True,
    )  # fmt: skip
    labeled, cpu = frames[0] - counted, cpu_seconds(pid) - cpu
    stop.set()
    thread.join()
    samples: Counter = Counter()
    for line in out.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        stage = stage_of(stack)
        if stage is not None:
            samples[stage] += int(count)
    # Each stage's share of the active samples times the server's CPU per frame: waiting for
    # a core (other processes on the machine) inflates samples, not shares.
    cpu_ms = 1000 * cpu / max(labeled, 1)
    total = sum(samples.values())
    ms = {name: cpu_ms * n / total for name, n in samples.items()}
    graphs = sum(ms.get(name, 0.0) for name in GRAPHS)
    return {"image": image, "store": store, "frames": labeled, "server_cpu_ms_per_frame": cpu_ms,
            "samples": total, "graphs_ms_per_frame": graphs,
            "stages_ms_per_frame": dict(sorted(ms.items(), key=lambda kv: -kv[1]))}  # fmt: skip


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=20.0, help="recorded per mode")
    parser.add_argument("--rate", type=int, default=200, help="samples per second")
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1,
                        help="onnxruntime threads per run (1: all its CPU sampled)")  # fmt: skip
    parser.add_argument("--images", nargs="+", choices=("png", "raw"), default=["png", "raw"],
                        help="how the client sends the image: the PNG files, or their pixels "
                        "uncompressed (raw_image)")  # fmt: skip
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    if shutil.which("py-spy") is None:
        parser.error("py-spy is not installed: pip install py-spy")
    work = Path(args.work or tempfile.mkdtemp(prefix="service_profile_"))
    repository = prepare_repository(work, args.config)
    results = []
    flags = ("--workers", str(args.workers), "--threads", str(args.threads))
    with serve(repository, work / "store", *flags) as server:
        for image in args.images:
            for store in (False, True):
                out = work / f"profile_{image}_store_{'on' if store else 'off'}.txt"
                results.append(profile(server.target, server.pid, args.seconds, store, args.rate,
                                       out, image))  # fmt: skip
    names = list(dict.fromkeys(n for r in results for n in r["stages_ms_per_frame"]))
    print(f"model {args.config}, {' '.join(flags)}, one client, {args.seconds:.0f} s per mode "
          f"at {args.rate} samples/s\n")  # fmt: skip
    columns = [f"{r['image']}, store {'on' if r['store'] else 'off'}" for r in results]
    print(f"| stage (ms / frame) | {' | '.join(columns)} |")
    print("| --- |" + " ---: |" * len(results))
    for name in names:
        cells = [f"{r['stages_ms_per_frame'].get(name, 0.0):.1f}" for r in results]
        print(f"| {name} | {' | '.join(cells)} |")
    for key, label in (("server_cpu_ms_per_frame", "server CPU (user + system)"),
                       ("graphs_ms_per_frame", "the two graphs")):  # fmt: skip
        print(f"| **{label}** | {' | '.join(f'{r[key]:.1f}' for r in results)} |")
    for r in results:
        ratio = r["server_cpu_ms_per_frame"] / r["graphs_ms_per_frame"]
        print(f"\n{r['image']}, store {'on' if r['store'] else 'off'}: {r['frames']} frames; "
              f"server CPU / graphs = {ratio:.2f}")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    print(f"\nrerun: {rerun('service_profile')}")


if __name__ == "__main__":
    main()
