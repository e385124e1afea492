"""Which layers an INT8 version keeps float: label agreement with fp32 of each choice, on train
frames only (issue 42, point 3; `export.quantize.float_layers` is the product's rule).

    python -m benchmarks.int8_layers --checkpoint RUN_OR_CKPT --data SYNTH_DIR [--split train]
        [--calibration-frames 32] [--agreement-frames 32] [--work DIR]

The checkpoint is exported once (fp32, version 000001); each choice quantizes both graphs as
`detmatch-export --quantize int8` does (QDQ, per-channel int8 weights, uint8 activations,
MinMax), calibrated on the same --calibration-frames frames of --split and compared with fp32
on --agreement-frames others of it (spread evenly, as the export draws them): the share of
fp32's matched labels reproduced (same class, 3D IoU >= 0.7 and 2D IoU >= 0.7). Choices:
every operator onnxruntime quantizes; convolutions and matrix products only (the product's
operator set, `QUANTIZED_OPS`), all of them, or with each graph's first layer float, its
heads' output layers float, both (the product's rule, `float_layers`), or the first and every
head layer float; and only one graph quantized (the other float).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from benchmarks.harness import benchmark_parser, rerun
from detmatch.data.kitti import KittiDataset, read_image_set
from detmatch.models.pillars import pillarize
from export.quantize import (
    QUANTIZED_OPS,
    _Feeds,
    consumers_of,
    float_layers,
    label_agreement,
)
from serving.labeler import INPUTS_3D, Labeler


def _first_layer(path: Path) -> list[str]:
    return float_layers(path)[:1]


def _output_layers(path: Path) -> list[str]:
    return float_layers(path)[1:]


def _first_and_head_layers(path: Path) -> list[str]:
    """The first layer and every head layer: a layer from which exactly one output layer (a
    quantizable node feeding no other) is reachable, the heads' chains after the shared
    features branch."""
    import onnx

    graph = onnx.load(str(path), load_external_data=False).graph
    consumers = consumers_of(graph)
    layers = [n for n in graph.node if n.op_type in QUANTIZED_OPS]
    reached: dict[str, set[str]] = {}
    for layer in layers:
        seen, found, stack = set(), set(), list(layer.output)
        while stack:
            for consumer in consumers.get(stack.pop(), []):
                if id(consumer) not in seen:
                    seen.add(id(consumer))
                    found |= {consumer.name} if consumer.op_type in QUANTIZED_OPS else set()
                    stack.extend(consumer.output)
        reached[layer.name] = found
    outputs = {name for name, found in reached.items() if not found}
    heads = [n.name for n in layers if len((reached[n.name] | {n.name}) & outputs) == 1]
    return _first_layer(path) + [n for n in heads if n not in _first_layer(path)]


# name -> (operator types (None: all onnxruntime quantizes), float nodes, graphs quantized)
Choice = tuple[list[str] | None, Callable[[Path], list[str]], tuple[str, ...]]
NONE: Callable[[Path], list[str]] = lambda path: []  # noqa: E731
CHOICES: dict[str, Choice] = {
    "every operator": (None, NONE, ("2d", "3d")),
    "convolutions and matrix products": (QUANTIZED_OPS, NONE, ("2d", "3d")),
    "... first layer float": (QUANTIZED_OPS, _first_layer, ("2d", "3d")),
    "... heads' output layers float": (QUANTIZED_OPS, _output_layers, ("2d", "3d")),
    "... first and output layers float (the product)": (QUANTIZED_OPS, float_layers,
                                                        ("2d", "3d")),
    "... first and every head layer float": (QUANTIZED_OPS, _first_and_head_layers,
                                             ("2d", "3d")),
    "2D graph only (the product's rule)": (QUANTIZED_OPS, float_layers, ("2d",)),
    "3D graph only (the product's rule)": (QUANTIZED_OPS, float_layers, ("3d",)),
}  # fmt: skip


def main() -> None:
    from onnxruntime.quantization import QuantFormat, QuantType, quantize_static

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
    wanted = args.calibration_frames + args.agreement_frames
    spread = ids[:: max(len(ids) // wanted, 1)][:wanted]
    dataset = KittiDataset(data)
    calibration = [
        dataset.load_frame(i, with_labels=False) for i in spread[: args.calibration_frames]
    ]
    held_out = [dataset.load_frame(i, with_labels=False) for i in spread[args.calibration_frames :]]
    reference = [fp32.label(f.image, f.points, f.calib) for f in held_out]
    feeds = {
        "2d": [{"image": np.ascontiguousarray(f.image)} for f in calibration],
        "3d": [dict(zip(INPUTS_3D, pillarize(f.points, fp32.grid).arrays, strict=True))
               for f in calibration],
    }  # fmt: skip
    specs = {"2d": fp32.manifest.model_2d, "3d": fp32.manifest.model_3d}
    rows = []
    for name, (op_types, excluded, graphs) in CHOICES.items():
        target = work / "choice"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(fp32.path, target)
        for graph in graphs:
            source = fp32.path / specs[graph].file
            quantize_static(
                str(source), str(target / specs[graph].file), _Feeds(feeds[graph]),
                quant_format=QuantFormat.QDQ, per_channel=True,
                activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                op_types_to_quantize=op_types, nodes_to_exclude=excluded(source),
            )  # fmt: skip
        candidate = Labeler(target, check_files=False)
        matched = reproduced = 0
        for frame, labels in zip(held_out, reference, strict=True):
            found = label_agreement(labels, candidate.label(frame.image, frame.points, frame.calib))
            matched, reproduced = matched + found[0], reproduced + found[1]
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
