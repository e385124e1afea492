"""INT8 against fp32 (`detmatch-export --quantize int8`): the graphs' speed at 1 and 2 threads,
the labels they agree on, and moderate mAP on val, measured in one run.

    python -m benchmarks.int8 --checkpoint RUN_OR_CKPT --data SYNTH_DIR [--work DIR]
        [--calibration-frames 32] [--agreement-frames 32] [--eval-frames 200]

The checkpoint is exported (fp32) and quantized (QDQ, per-channel, first and last layers
float) into a repository in --work, calibrated and checked on frames of the data set's train
split (`ImageSets/train.txt`); `--min-agreement 0` publishes it whatever it scores, so the
figures are reported even where `detmatch-export` would refuse it. Then, on --eval-frames of
the val split (scored once, never used for a choice): each graph's time per call, fp32 and
INT8 alternating, with 1 and 2 onnxruntime threads; both versions label the frames, and
`detmatch eval`'s KITTI scoring gives each one's moderate R40 mAP (3D for the 3D labels, 2D
bbox for the matched labels' 2D boxes). Targets (issue 42): INT8 graphs >= 2x faster, mAP
within 1.0 of fp32 in both modalities, >= 95 % of fp32's matched labels reproduced.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import benchmark_parser, rerun
from detmatch.data.kitti import KittiDataset, read_image_set
from detmatch.data.selection import FrameSelection
from detmatch.eval.kitti import evaluate_dirs


def graph_times(paths: dict[str, Path], feeds: list[dict], threads: int, rounds: int) -> dict:
    """Milliseconds per call of each graph, the graphs alternating round by round."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    sessions = {name: ort.InferenceSession(str(path), options,
                                           providers=["CPUExecutionProvider"])
                for name, path in paths.items()}  # fmt: skip
    times = {name: [] for name in paths}
    for session in sessions.values():
        session.run(None, feeds[0])
    for _ in range(rounds):
        for name, session in sessions.items():
            start = time.perf_counter()
            for feed in feeds:
                session.run(None, feed)
            times[name].append((time.perf_counter() - start) / len(feeds) * 1000)
    return {name: float(np.median(values)) for name, values in times.items()}


def moderate_maps(labeler, data: Path, ids: list[str], out: Path) -> dict[str, float]:
    from serving.offline import label_split

    (out).mkdir(parents=True, exist_ok=True)
    (out / "ids.txt").write_text("".join(f"{i}\n" for i in ids))
    label_split(labeler, data, FrameSelection(ids_file=out / "ids.txt"), out, progress=False)
    classes = list(labeler.classes)
    maps = {}
    for modality, metric in (("3d", "3d"), ("2d", "bbox")):
        results = evaluate_dirs(data / "training" / "label_2", out / modality, ids, classes)
        maps[modality] = float(np.mean([results[c]["R40"][metric][1] for c in classes]))
    return maps


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--calibration-frames", type=int, default=32)
    parser.add_argument("--agreement-frames", type=int, default=32)
    parser.add_argument("--eval-frames", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=5, help="timing rounds per thread count")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    from export.onnx_export import export_checkpoint
    from export.quantize import graph_feeds, quantize_version
    from serving.labeler import Labeler

    work = Path(args.work or tempfile.mkdtemp(prefix="int8_"))
    repository, data = work / "models", Path(args.data)
    if not (repository / "000001").is_dir():
        export_checkpoint(args.checkpoint, repository, version=1, synthetic_frames=1,
                          parity_frames_per_source=1)  # fmt: skip
    if not (repository / "000002").is_dir():
        quantize_version(repository, "000001", data, args.calibration_frames,
                         args.agreement_frames, min_agreement=0.0, version="000002",
                         frames=read_image_set(data / "ImageSets" / "train.txt"),
                         log=print)  # fmt: skip
    fp32, int8 = Labeler(repository / "000001"), Labeler(repository / "000002")
    record = int8.manifest.quantization
    val = read_image_set(data / "ImageSets" / "val.txt")[: args.eval_frames]
    dataset = KittiDataset(data)
    sample = [dataset.load_frame(i, with_labels=False) for i in val[:8]]
    feeds = graph_feeds(sample, fp32.grid)
    speed = {}
    for threads in (1, 2):
        for graph, spec in (("2d", "model_2d"), ("3d", "model_3d")):
            file = getattr(fp32.manifest, spec).file
            speed[(threads, graph)] = graph_times(
                {"fp32": fp32.path / file, "int8": int8.path / file}, feeds[graph], threads,
                args.rounds,
            )  # fmt: skip
    maps = {name: moderate_maps(labeler, data, val, work / f"labels_{name}")
            for name, labeler in (("fp32", fp32), ("int8", int8))}  # fmt: skip
    print(f"{args.checkpoint} on {data}: calibrated on {record.calibration_frames} train frames")
    print("\n| graph | threads | fp32 ms | INT8 ms | fp32 / INT8 |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for (threads, graph), times in speed.items():
        print(f"| {graph} | {threads} | {times['fp32']:.1f} | {times['int8']:.1f} | "
              f"{times['fp32'] / times['int8']:.2f} |")  # fmt: skip
    print(f"\nlabel agreement ({record.parity_frames} train frames): {record.reproduced} of "
          f"{record.matched_labels} fp32 matched labels reproduced ({record.agreement:.1%}; "
          "target >= 95 %)")  # fmt: skip
    print(f"\n| val ({len(val)} frames), moderate R40 mAP | fp32 | INT8 | difference |")
    print("| --- | ---: | ---: | ---: |")
    for modality in ("3d", "2d"):
        a, b = maps["fp32"][modality], maps["int8"][modality]
        print(f"| {modality.upper()} | {a:.2f} | {b:.2f} | {b - a:+.2f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "speed": {f"{g}@{t}": v for (t, g), v in speed.items()}, "maps": maps,
            "agreement": record.agreement}, indent=2) + "\n")  # fmt: skip
    argv = ["--checkpoint", args.checkpoint, "--data", args.data, "--calibration-frames",
            str(args.calibration_frames), "--agreement-frames", str(args.agreement_frames),
            "--eval-frames", str(args.eval_frames)]  # fmt: skip
    print(f"\nrerun: {rerun('int8', argv)}")


if __name__ == "__main__":
    main()
