"""onnxruntime's memory arena on and off: what one large image leaves behind, and what turning
the arena off costs on normal frames.

    python -m benchmarks.service_memory [--repeats 30] [--config configs/synth_cpu.toml]

For each setting a fresh process (torch blocked) loads the labeler with the arena on or off
and runs `Labeler.label` on the three KITTI sample frames (--repeats calls after 3 warm-up
calls: median and p90 latency), then once on a frame whose image is the largest the server
accepts by default (3840 x 2160, `serving.decode.DEFAULT_MAX_IMAGE_PIXELS`), then on the
sample frames again. Figures: RSS after the normal frames, after the large one, and after the
normal frames that follow (what the large image left behind), and the latency ratio off / on
of the two settings' medians, measured in alternating runs. The server runs with the arena
off (`serving/sessions.py`); it used to keep about 1.2 GB after one 8192 x 8192 image.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import REPO, prepare_repository

WARM_UP = 3


def worker(version_dir: str, arena: bool, repeats: int) -> dict:
    sys.modules["torch"] = None
    import os

    from benchmarks.service_common import KITTI_SAMPLE, SAMPLE_IDS, rss_mib
    from detmatch.data.kitti import KittiDataset
    from serving.decode import DEFAULT_MAX_IMAGE_PIXELS
    from serving.labeler import Labeler
    from serving.sessions import SessionSettings

    labeler = Labeler(Path(version_dir), SessionSettings(memory_arena=arena))
    dataset = KittiDataset(KITTI_SAMPLE)
    frames = [dataset.load_frame(i, with_labels=False) for i in SAMPLE_IDS]
    pid = os.getpid()

    def run_normal(count: int) -> list[float]:
        times = []
        for i in range(count):
            frame = frames[i % len(frames)]
            start = time.perf_counter()
            labeler.label(frame.image, frame.points, frame.calib)
            times.append(time.perf_counter() - start)
        return times

    run_normal(WARM_UP)
    times = run_normal(repeats)
    normal = rss_mib(pid)
    width = 3840
    height = DEFAULT_MAX_IMAGE_PIXELS // width
    large = np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)
    frame = frames[0]
    labeler.label(large, frame.points, frame.calib)
    after_large = rss_mib(pid)
    times += run_normal(repeats)
    return {
        "median_ms": 1000 * float(np.median(times)),
        "p90_ms": 1000 * float(np.percentile(times, 90)),
        "rss_normal_mib": normal,
        "rss_after_large_mib": after_large,
        "rss_after_normal_again_mib": rss_mib(pid),
        "large": f"{width} x {height}",
    }


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=2, help="alternating runs per setting")
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--arena", choices=("on", "off"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.arena == "on", args.repeats)))
        return
    work = Path(args.work or tempfile.mkdtemp(prefix="service_memory_"))
    version = prepare_repository(work, args.config) / "000001"
    results: dict[str, list[dict]] = {"on": [], "off": []}
    for _ in range(args.rounds):
        for arena in ("on", "off"):
            command = [sys.executable, "-m", "benchmarks.service_memory", "--worker",
                       str(version), "--arena", arena, "--repeats",
                       str(args.repeats)]  # fmt: skip
            env = {"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
            done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, check=True,
                                  env=env)  # fmt: skip
            results[arena].append(json.loads(done.stdout.strip().splitlines()[-1]))
    print(f"model {args.config}, labeler on the 3 KITTI sample frames, {args.repeats} calls "
          f"per phase, {args.rounds} alternating runs per setting; the large image: "
          f"{results['on'][0]['large']}")  # fmt: skip
    print("\n| arena | median ms | p90 ms | RSS MiB: normal frames | after the large image | "
          "after normal frames again |")  # fmt: skip
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for arena, runs in results.items():
        for run in runs:
            print(f"| {arena} | {run['median_ms']:.1f} | {run['p90_ms']:.1f} | "
                  f"{run['rss_normal_mib']:.0f} | {run['rss_after_large_mib']:.0f} | "
                  f"{run['rss_after_normal_again_mib']:.0f} |")  # fmt: skip
    on = np.median([r["median_ms"] for r in results["on"]])
    off = np.median([r["median_ms"] for r in results["off"]])
    print(f"\nlatency with the arena off / on: {off / on:.3f}")
    argv = ["--repeats", str(args.repeats), "--rounds", str(args.rounds), "--config",
            args.config]  # fmt: skip
    print(f"\nrerun: {rerun('service_memory', argv)}")


if __name__ == "__main__":
    main()
