"""The most dynamic batching can save on this machine: each served graph's time per frame when
B frames go through one call, against one frame a call (issue 42, point 4).

    python -m benchmarks.batching [--config configs/synth_cpu.toml] [--batches 1 2 4 8]
        [--threads 1 2] [--data tests/data/kitti]

Both detectors of the config (fresh weights: the time does not depend on them) are exported
as the service serves them (`export.graphs`: a dynamic batch axis, the 2D graph's resize and
both graphs' decoding inside) and run in the labeler's onnxruntime sessions
(`serving.sessions`) on 1 and 2 intra-op threads: the 2D graph on B copies of a full-resolution
KITTI image (a batch holds images of one size), the 3D graph on the pillars of the data's
frames in turn, padded as the labeler pads them (`batch_pillars`). A figure is the median of
the calls, after two warm-up calls, in ms per frame; the last column divides it by the same
frames' time one call each: batching wins where that is below 1.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import benchmark_parser, rerun
from detmatch.config import load_config
from detmatch.data.kitti import KittiDataset
from detmatch.models.build import build_detectors
from detmatch.models.pillars import batch_pillars, pillarize
from export.graphs import export_detector_2d, export_detector_3d
from serving.repository import INPUTS_3D
from serving.sessions import SessionSettings, make_session


def _ms_per_frame(path: Path, feed: dict[str, np.ndarray], threads: int, batch: int) -> float:
    session = make_session(path, SessionSettings(intra_op_threads=threads))
    for _ in range(2):
        session.run(None, feed)
    times = []
    for _ in range(max(5, 32 // batch)):
        start = time.perf_counter()
        session.run(None, feed)
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times)) / batch


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--data", default="tests/data/kitti",
                        help="KITTI-layout frames: the first one's image, all their "
                        "pillars")  # fmt: skip
    args = parser.parse_args()
    torch.manual_seed(0)
    config = load_config(args.config)
    model_2d, model_3d = (m.eval() for m in build_detectors(config))
    dataset = KittiDataset(args.data)
    frames = [dataset.load_frame(i, with_labels=False) for i in dataset.ids()]
    pillars = [pillarize(f.points, model_3d.grid) for f in frames]
    figures: dict[tuple[str, int, int], float] = {}
    with tempfile.TemporaryDirectory(prefix="batching_") as scratch:
        path_2d, path_3d = Path(scratch) / "2d.onnx", Path(scratch) / "3d.onnx"
        export_detector_2d(model_2d, config.data.image_size, path_2d, frames[0].image)
        export_detector_3d(model_3d, path_3d, pillars[0].arrays)
        single_3d = {threads: [_ms_per_frame(path_3d, dict(zip(INPUTS_3D, batch_pillars([p]),
                                                                strict=True)), threads, 1)
                               for p in pillars]
                     for threads in args.threads}  # fmt: skip
        for batch in args.batches:
            feed_2d = {"image": np.stack([frames[0].image] * batch)}
            chosen = [pillars[i % len(pillars)] for i in range(batch)]
            feed_3d = dict(zip(INPUTS_3D, batch_pillars(chosen), strict=True))
            for threads in args.threads:
                figures["2D", threads, batch] = _ms_per_frame(path_2d, feed_2d, threads, batch)
                figures["3D", threads, batch] = _ms_per_frame(path_3d, feed_3d, threads, batch)
                # One call per frame for the same frames: the baseline of this batch.
                alone = np.mean([single_3d[threads][i % len(pillars)] for i in range(batch)])
                figures["3D alone", threads, batch] = float(alone)
                figures["2D alone", threads, batch] = figures["2D", threads, 1]
    width, height = frames[0].image_size
    print(f"{args.config}: the served graphs; 2D on {width} x {height} images resized to "
          f"{config.data.image_size[0]} x {config.data.image_size[1]}, 3D on "
          f"{', '.join(str(len(p)) for p in pillars)} pillars a frame ({args.data}), a batch "
          "taking them in turn; ms per frame, median")  # fmt: skip
    print("\n| graph | threads | " + " | ".join(f"B = {b}" for b in args.batches)
          + " | B = " + " / ".join(map(str, args.batches)) + ": batch / alone |")  # fmt: skip
    print("| --- | ---: |" + " ---: |" * (len(args.batches) + 1))
    for name in ("2D", "3D"):
        for threads in args.threads:
            row = [figures[name, threads, b] for b in args.batches]
            ratios = [figures[name, threads, b] / figures[f"{name} alone", threads, b]
                      for b in args.batches]  # fmt: skip
            print(f"| {name} | {threads} | " + " | ".join(f"{v:.1f}" for v in row)
                  + " | " + " / ".join(f"{r:.2f}" for r in ratios) + " |")  # fmt: skip
    argv = ["--config", args.config, "--batches", *map(str, args.batches), "--threads",
            *map(str, args.threads), "--data", args.data]  # fmt: skip
    print(f"\nrerun: {rerun('batching', argv)}")


if __name__ == "__main__":
    main()
