"""Data loading speed of the pre-training stream: labeled frames with the config's [augment]
(ground-truth sampling, rotation and scale, flip, multi-scale window) made into samples, one
thread, the way a data worker (or a run without workers) does it.

    python -m benchmarks.loader_speed --config configs/ssl_cpu.toml --data data/synth2k \
        [--frames 40] [--rounds 3]

Prints milliseconds per frame (median of the rounds) and the command to rerun. To compare
with an older checkout, run this file against it (old-vs-new ratios in one farm-bench run):

    OLD="PYTHONPATH=/path/to/old exec python -m benchmarks.loader_speed --data data/synth2k"
    farm-bench -n 5 --timeout 300 --vs "sh -c '$OLD'" \
        -- python -m benchmarks.loader_speed --data data/synth2k
"""

from __future__ import annotations

import statistics
import time

import torch

from benchmarks.harness import benchmark_parser, rerun
from detmatch.config import load_config
from detmatch.models.build import build_detectors
from detmatch.training.trainer import labeled_training_frames


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--config", default="configs/ssl_cpu.toml")
    parser.add_argument("--data", required=True)
    parser.add_argument("--frames", type=int, default=40, help="samples a round")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)  # a data worker's share

    config = load_config(args.config).replace("data", root=args.data)
    data = config.data
    grid = build_detectors(config)[1].grid
    started = time.perf_counter()
    dataset = labeled_training_frames(config, grid)
    setup = time.perf_counter() - started
    per_frame = []
    for round_ in range(args.rounds):
        started = time.perf_counter()
        for i in range(args.frames):
            draw = round_ * args.frames + i
            dataset[(draw % len(dataset), draw)]
        per_frame.append((time.perf_counter() - started) / args.frames * 1000)
    print(f"split {data.train_split}: {len(dataset)} frames, set-up {setup:.1f} s")
    print(f"pre-training sample: {statistics.median(per_frame):.1f} ms a frame "
          f"(rounds: {', '.join(f'{t:.1f}' for t in per_frame)})")  # fmt: skip
    print(f"rerun: {rerun('loader_speed')}")


if __name__ == "__main__":
    main()
