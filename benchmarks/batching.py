"""The most dynamic batching can save on this machine: each detector's graph time per frame
when B frames go through one call, against one frame a call (issue 42, point 4).

    python -m benchmarks.batching [--config configs/synth_cpu.toml] [--batches 1 2 4 8]
        [--threads 1 2] [--frame tests/data/kitti:000000]

Both detectors of the config (fresh weights: the time does not depend on them) are exported to
ONNX at each fixed batch size B: the 2D detector on (B, 3, H, W) input images of the config's
[data] image_size, the 3D detector on B copies of one frame's pillars (batch index in the
coordinates, one canvas of B frames, as training batches them). onnxruntime times each on 1
and 2 intra-op threads (median of the calls, after two warm-up calls); a figure is ms per
frame, so batching wins where B > 1 is below B = 1. The graphs are the models alone, without
the in-graph image resize and box decoding the served graphs add: those do not batch either.
"""

from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from benchmarks.harness import benchmark_parser, rerun
from detmatch.config import load_config
from detmatch.data.kitti import KittiDataset
from detmatch.models.build import build_detectors
from detmatch.models.pillars import pillarize


class _Batched3D(torch.nn.Module):
    def __init__(self, detector: torch.nn.Module, batch: int) -> None:
        super().__init__()
        self.detector, self.batch = detector, batch

    def forward(self, features, coords, counts):
        return self.detector(features, coords, counts, batch_size=self.batch)[:2]


def _export(module: torch.nn.Module, inputs: tuple[np.ndarray, ...], path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, tuple(torch.from_numpy(a) for a in inputs), str(path),
                          dynamo=False, opset_version=17)  # fmt: skip


def _ms_per_frame(path: Path, inputs: tuple[np.ndarray, ...], threads: int, batch: int) -> float:
    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    feed = dict(zip((i.name for i in session.get_inputs()), inputs, strict=True))
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
    parser.add_argument("--frame", default="tests/data/kitti:000000",
                        help="DATA:ID, the frame whose pillars the 3D graph batches")  # fmt: skip
    args = parser.parse_args()
    torch.manual_seed(0)
    config = load_config(args.config)
    model_2d, model_3d = (m.eval() for m in build_detectors(config))
    width, height = config.data.image_size
    data, frame_id = args.frame.rsplit(":", 1)
    frame = KittiDataset(data).load_frame(frame_id)
    features, coords, counts = pillarize(frame.points.astype(np.float32), model_3d.grid).arrays
    rng = np.random.default_rng(0)
    figures: dict[tuple[str, int, int], float] = {}
    with tempfile.TemporaryDirectory(prefix="batching_") as scratch:
        for batch in args.batches:
            image = rng.random((batch, 3, height, width), dtype=np.float32)
            pillars = (
                np.concatenate([features] * batch),
                np.concatenate([np.concatenate([np.full((len(coords), 1), b), coords], axis=1)
                                for b in range(batch)]).astype(np.int64),
                np.concatenate([counts] * batch),
            )  # fmt: skip
            path_2d, path_3d = (
                Path(scratch) / f"2d_{batch}.onnx",
                Path(scratch) / f"3d_{batch}.onnx",
            )
            _export(model_2d, (image,), path_2d)
            _export(_Batched3D(model_3d, batch), pillars, path_3d)
            for threads in args.threads:
                figures["2D", threads, batch] = _ms_per_frame(path_2d, (image,), threads, batch)
                figures["3D", threads, batch] = _ms_per_frame(path_3d, pillars, threads, batch)
    print(f"{args.config}: 2D input {width} x {height}, 3D {len(features)} pillars a frame "
          f"({args.frame}); ms per frame, median")  # fmt: skip
    print("\n| graph | threads | " + " | ".join(f"B = {b}" for b in args.batches)
          + " | best B > 1 / B = 1 |")  # fmt: skip
    print("| --- | ---: |" + " ---: |" * (len(args.batches) + 1))
    for name in ("2D", "3D"):
        for threads in args.threads:
            row = [figures[name, threads, b] for b in args.batches]
            best = min(row[1:]) / row[0] if len(row) > 1 else 1.0
            print(f"| {name} | {threads} | " + " | ".join(f"{v:.1f}" for v in row)
                  + f" | {best:.2f} |")  # fmt: skip
    print(f"\nrerun: {rerun('batching')}")


if __name__ == "__main__":
    main()
