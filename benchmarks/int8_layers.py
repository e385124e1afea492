"""Which layers an INT8 version keeps float: label agreement with fp32 of each choice, on train
frames only (issue 42, point 3; `export.quantize.float_layers` is the product's rule).

    python -m benchmarks.int8_layers --checkpoint RUN_OR_CKPT --data SYNTH_DIR [--split train]
        [--calibration-frames 32] [--agreement-frames 32] [--work DIR]

The checkpoint is exported once (fp32, version 000001); each choice quantizes both graphs as
`detmatch-export --quantize int8` does (QDQ, per-channel int8 weights, uint8 activations,
MinMax: each activation's range the moving average of the frames' ranges), calibrated on the
same --calibration-frames frames of --split and compared with fp32 on --agreement-frames
others of it (spread evenly, as the export draws them): the share of
fp32's matched labels reproduced (same class, 3D IoU >= 0.7 and 2D IoU >= 0.7). Choices:
every operator onnxruntime quantizes; convolutions and matrix products only (the product's
operator set, `QUANTIZED_OPS`), all of them, or with each graph's first layer float, its
heads' output layers float, both (the product's rule, `float_layers`), or the first and every
head layer float; the product's rule with activation ranges from every frame's extremes (the
calibration before 2026-12-07); and only one graph quantized (the other float).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from benchmarks.harness import benchmark_parser, rerun
from detmatch.data.kitti import KittiDataset, read_image_set
from export.quantize import (
    QUANTIZED_OPS,
    agreement_on,
    float_layers,
    graph_feeds,
    quantizable_layers,
    quantize_graph,
    spread_frames,
)
from serving.labeler import Labeler


def _first_layer(path: Path) -> list[str]:
    return float_layers(path)[:1]


def _output_layers(path: Path) -> list[str]:
    return float_layers(path)[1:]


def _first_and_head_layers(path: Path) -> list[str]:
    """The first layer and every head layer: a layer from which exactly one output layer (a
    quantizable node feeding no other) is reachable, the heads' chains after the shared
    features branch."""
    reached = quantizable_layers(path)
    outputs = {name for name, found in reached.items() if not found}
    heads = [name for name, found in reached.items() if len((found | {name}) & outputs) == 1]
    return _first_layer(path) + [n for n in heads if n not in _first_layer(path)]


# name -> (operator types (None: all onnxruntime quantizes), float nodes, graphs quantized,
# activation ranges from the moving average of each frame's range (else every frame's extremes))
Choice = tuple[list[str] | None, Callable[[Path], list[str]], tuple[str, ...], bool]
NONE: Callable[[Path], list[str]] = lambda path: []  # noqa: E731
CHOICES: dict[str, Choice] = {
    "every operator": (None, NONE, ("2d", "3d"), True),
    "convolutions and matrix products": (QUANTIZED_OPS, NONE, ("2d", "3d"), True),
    "... first layer float": (QUANTIZED_OPS, _first_layer, ("2d", "3d"), True),
    "... heads' output layers float": (QUANTIZED_OPS, _output_layers, ("2d", "3d"), True),
    "... first and output layers float, ranges from every frame's extremes": (
        QUANTIZED_OPS, float_layers, ("2d", "3d"), False),
    "... first and output layers float (the product)": (QUANTIZED_OPS, float_layers,
                                                        ("2d", "3d"), True),
    "... first and every head layer float": (QUANTIZED_OPS, _first_and_head_layers,
                                             ("2d", "3d"), True),
    "2D graph only (the product's rule)": (QUANTIZED_OPS, float_layers, ("2d",), True),
    "3D graph only (the product's rule)": (QUANTIZED_OPS, float_layers, ("3d",), True),
}  # fmt: skip


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", default="train", help="the frames to draw from (never val)")
    parser.add_argument("--calibration-frames", type=int, default=32)
    parser.add_argument("--agreement-frames", type=int, default=32)
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    args = parser.parse_args()
    if args.split in ("val", "test"):
        parser.error("--split val: choices are made on train frames, never on val")
    from export.onnx_export import export_checkpoint

    work = Path(args.work or tempfile.mkdtemp(prefix="int8_layers_"))
    repository, data = work / "models", Path(args.data)
    if not (repository / "000001").is_dir():
        export_checkpoint(args.checkpoint, repository, version=1, synthetic_frames=1,
                          parity_frames_per_source=1)  # fmt: skip
    fp32 = Labeler(repository / "000001")
    ids = read_image_set(data / "ImageSets" / f"{args.split}.txt")
    spread = spread_frames(ids, args.calibration_frames + args.agreement_frames)
    dataset = KittiDataset(data)
    calibration = [
        dataset.load_frame(i, with_labels=False) for i in spread[: args.calibration_frames]
    ]
    held_out = [dataset.load_frame(i, with_labels=False) for i in spread[args.calibration_frames :]]
    reference = [fp32.label(f.image, f.points, f.calib) for f in held_out]
    feeds = graph_feeds(calibration, fp32.grid)
    specs = {"2d": fp32.manifest.model_2d, "3d": fp32.manifest.model_3d}
    rows = []
    for name, (op_types, excluded, graphs, moving_average) in CHOICES.items():
        target = work / "choice"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(fp32.path, target)
        for graph in graphs:
            source = fp32.path / specs[graph].file
            quantize_graph(source, target / specs[graph].file, feeds[graph], excluded(source),
                           op_types, moving_average)  # fmt: skip
        candidate = Labeler(target, check_files=False)
        matched, reproduced = agreement_on(reference, candidate, held_out)
        rows.append((name, reproduced, matched))
        print(f"{name}: {reproduced} of {matched} ({reproduced / max(matched, 1):.1%})", flush=True)
    print(f"\n{args.checkpoint} on {data} ({args.split}): calibrated on {len(calibration)} frames, "
          f"compared on {len(held_out)} others\n")  # fmt: skip
    print("| layers quantized | fp32 matched labels reproduced | agreement |")
    print("| --- | ---: | ---: |")
    for name, reproduced, matched in rows:
        print(f"| {name} | {reproduced} of {matched} | {reproduced / max(matched, 1):.1%} |")
    argv = ["--checkpoint", args.checkpoint, "--data", args.data, "--split", args.split,
            "--calibration-frames", str(args.calibration_frames), "--agreement-frames",
            str(args.agreement_frames)]  # fmt: skip
    print(f"\nrerun: {rerun('int8_layers', argv)}")


if __name__ == "__main__":
    main()
