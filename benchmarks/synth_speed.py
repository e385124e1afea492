"""Synthetic data generation speed: frames per second at half and full resolution, 1 and 2
worker processes, whole frames written to disk (sampling, ray casting, labels, PNG, .bin).

    python -m benchmarks.synth_speed [--frames N] [--seed S]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import benchmark_parser, rerun
from detmatch.data.synth import generate_dataset


def measure(frames: int, seed: int, resolution: str, workers: int) -> float:
    """Seconds to write `frames` frames (including worker start-up)."""
    with tempfile.TemporaryDirectory() as directory:
        start = time.perf_counter()
        generate_dataset(Path(directory), frames, seed, resolution, workers, 0.25, progress=False)
        return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--frames", type=int, default=16, help="frames per measurement")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    measure(1, args.seed, "half", 1)  # warm the imports and caches
    rows = []
    for resolution in ("half", "full"):
        for workers in (1, 2):
            seconds = measure(args.frames, args.seed, resolution, workers)
            rows.append((resolution, workers, seconds, args.frames / seconds))
    print(f"{'resolution':<11}{'workers':>8}{'seconds':>10}{'frames/s':>10}{'per worker':>12}")
    for resolution, workers, seconds, rate in rows:
        print(f"{resolution:<11}{workers:>8}{seconds:>10.2f}{rate:>10.2f}{rate / workers:>12.2f}")
    print(f"\n{args.frames} frames each; rerun: {rerun('synth_speed', argv)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
