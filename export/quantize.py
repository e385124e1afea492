"""An INT8 version of a published model version (`detmatch-export --quantize int8`).

quantize_version(repository, source_version, calibration_data)
  1. both graphs of the source (fp32) version through onnxruntime's static quantization: QDQ
     format, per-channel int8 weights, uint8 activations calibrated (MinMax, each
     activation's range the moving average of the frames' minima and maxima, not their
     extremes), convolutions and matrix products but the first and last layers
     (`float_layers`), on
     `calibration_frames` frames of a KITTI-layout directory (the training data, a label
     store export), fed exactly as the labeler feeds the graphs;
  2. label parity on `parity_frames` other frames of the same directory: the fp32 and INT8
     labelers label each, and the share of the fp32 version's matched labels that the INT8
     version reproduces (same 3D class, 3D IoU >= 0.7 and 2D IoU >= 0.7) must reach
     `min_agreement` (default 0.95), else ExportCheckError and nothing is published;
  3. a new version: the source's manifest (format 3) with the INT8 files' checksums and a
     `quantization` record (scheme, source version, calibration and parity figures).
The labeler serves it like any version; promote it to serve it.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from detmatch.data.kitti import KittiDataset
from detmatch.geometry import pairwise_iou_2d, pairwise_iou_3d
from detmatch.models.pillars import batch_pillars, pillarize
from export.graphs import ExportCheckError
from serving.labeler import INPUTS_3D, Labeler
from serving.manifest import QuantizationRecord
from serving.repository import file_record, promote, publish, staging_directory, version_dir

SCHEME = (
    "int8 static (onnxruntime), QDQ, per-channel int8 weights, uint8 activations (MinMax, "
    "moving average); "
    "convolutions and matrix products but each graph's first and last layers"
)
MIN_AGREEMENT = 0.95
# The convolutions and matrix products only: the graphs' in-graph pre- and post-processing
# (resize, normalisation, peak finding, top-k, box decoding) stays float, and so do each
# graph's first and last layers (`float_layers`): quantizing the pillar encoder's linear
# layer or the heads' output convolutions cost 10-15 points of label agreement on a
# pre-trained synthetic model (BENCHMARKS.md, "INT8 models").
QUANTIZED_OPS = ["Conv", "ConvTranspose", "MatMul", "Gemm"]
IOU_3D, IOU_2D = 0.7, 0.7


@dataclass(frozen=True)
class QuantizeResult:
    version: str
    path: Path
    promoted: bool
    record: QuantizationRecord


class _Feeds:
    """onnxruntime's CalibrationDataReader over prepared input feeds."""

    def __init__(self, feeds: list[dict[str, np.ndarray]]) -> None:
        self._feeds = iter(feeds)

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._feeds, None)


def quantizable_layers(model_path: Path) -> dict[str, set[str]]:
    """An ONNX file's quantizable nodes (QUANTIZED_OPS), in graph order -> the quantizable
    nodes reachable from each."""
    import onnx

    graph = onnx.load(str(model_path), load_external_data=False).graph
    consumers: dict[str, list] = {}  # tensor name -> the nodes that read it
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    reached: dict[str, set[str]] = {}
    for layer in (n for n in graph.node if n.op_type in QUANTIZED_OPS):
        seen, found, stack = set(), set(), list(layer.output)
        while stack:
            for consumer in consumers.get(stack.pop(), []):
                if id(consumer) not in seen:
                    seen.add(id(consumer))
                    if consumer.op_type in QUANTIZED_OPS:
                        found.add(consumer.name)
                    stack.extend(consumer.output)
        reached[layer.name] = found
    return reached


def float_layers(model_path: Path) -> list[str]:
    """The quantizable nodes that stay float: the first one (in graph order) and every one
    from which no other quantizable node is reachable (the heads' output layers)."""
    reached = quantizable_layers(model_path)
    first = list(reached)[:1]
    return first + [name for name, found in reached.items() if not found and name not in first]


def spread_frames(ids: list[str], count: int) -> list[str]:
    """count ids spread evenly over ids (the first count if there are fewer)."""
    return ids[:: max(len(ids) // count, 1)][:count]


def graph_feeds(frames, grid) -> dict[str, list[dict[str, np.ndarray]]]:
    """Frames -> each graph's input feeds ("2d", "3d"), as the labeler feeds the graphs."""
    return {
        "2d": [{"image": np.ascontiguousarray(f.image[None])} for f in frames],
        "3d": [dict(zip(INPUTS_3D, batch_pillars([pillarize(f.points, grid)]), strict=True))
               for f in frames],
    }  # fmt: skip


def quantize_graph(
    source: Path,
    target: Path,
    feeds: list[dict[str, np.ndarray]],
    nodes_to_exclude: list[str],
    op_types: list[str] | None = QUANTIZED_OPS,
    moving_average: bool = True,
) -> None:
    """One graph through onnxruntime's static quantization as SCHEME says (op_types None:
    every operator it quantizes), calibrated on feeds. moving_average: an activation's range
    is the moving average of each frame's minimum and maximum (the default: a rare extreme
    frame no longer stretches the range, 94.5 -> 96.6 % label agreement, BENCHMARKS.md);
    False: the extremes over every frame."""
    from onnxruntime.quantization import QuantFormat, QuantType, quantize_static

    quantize_static(
        str(source), str(target), _Feeds(feeds), quant_format=QuantFormat.QDQ,
        per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
        op_types_to_quantize=op_types, nodes_to_exclude=nodes_to_exclude,
        extra_options={"CalibMovingAverage": moving_average},
    )  # fmt: skip


def agreement_on(references, candidate: Labeler, frames) -> tuple[int, int]:
    """label_agreement summed over frames: references[i], the reference version's labels of
    frames[i], against the candidate's labels of it."""
    matched = reproduced = 0
    for frame, reference in zip(frames, references, strict=True):
        found = label_agreement(reference, candidate.label(frame.image, frame.points, frame.calib))
        matched, reproduced = matched + found[0], reproduced + found[1]
    return matched, reproduced


def label_agreement(reference, candidate) -> tuple[int, int]:
    """(the reference's matched labels, how many of them the candidate reproduces: a matched
    label of the same 3D class with 3D IoU >= 0.7 and 2D IoU >= 0.7, each used once)."""
    ref, cand = reference.labels, candidate.labels
    ref_rows = np.flatnonzero(ref.matched)
    cand_rows = np.flatnonzero(cand.matched)
    if not len(ref_rows) or not len(cand_rows):
        return len(ref_rows), 0
    iou_3d = pairwise_iou_3d(ref.boxes_3d[ref_rows], cand.boxes_3d[cand_rows])
    iou_2d = pairwise_iou_2d(ref.boxes_2d[ref_rows], cand.boxes_2d[cand_rows])
    same = ref.class_3d[ref_rows][:, None] == cand.class_3d[cand_rows][None, :]
    ok = same & (iou_3d >= IOU_3D) & (iou_2d >= IOU_2D)
    taken, found = set(), 0
    for i in range(len(ref_rows)):
        for j in np.argsort(-iou_3d[i]):
            if ok[i, j] and int(j) not in taken:
                taken.add(int(j))
                found += 1
                break
    return len(ref_rows), found


def quantize_version(
    repository: str | Path,
    source_version: str,
    calibration_data: str | Path,
    calibration_frames: int = 32,
    parity_frames: int = 32,
    min_agreement: float = MIN_AGREEMENT,
    version: str | None = None,
    promote_version: bool = False,
    log: Callable[[str], None] | None = None,
    frames: list[str] | None = None,
) -> QuantizeResult:
    """Quantize, check and publish (see the module docstring). frames: the ids of
    calibration_data to draw the calibration and agreement frames from (default: all)."""
    log = log or (lambda message: None)
    if not 0.0 <= min_agreement <= 1.0:
        raise ValueError(f"min_agreement must be in [0, 1], got {min_agreement}")
    repository = Path(repository)
    source = Labeler(version_dir(repository, source_version))
    if source.manifest.quantization is not None:
        raise ValueError(f"version {source.version} is quantized already")
    dataset = KittiDataset(calibration_data)
    ids = dataset.ids() if frames is None else list(frames)
    if len(ids) < calibration_frames + parity_frames:
        raise ValueError(
            f"{calibration_data} has {len(ids)} frames; calibration and parity need "
            f"{calibration_frames} + {parity_frames}"
        )
    spread = spread_frames(ids, calibration_frames + parity_frames)
    calibration, held_out = spread[:calibration_frames], spread[calibration_frames:]
    frames = [dataset.load_frame(i, with_labels=False) for i in calibration]
    feeds = graph_feeds(frames, source.grid)
    started = time.time()
    with staging_directory(repository) as staging:
        for item in source.path.iterdir():
            if item.name != "PROMOTED" and item.is_file():
                shutil.copyfile(item, staging / item.name)
        for graph, spec in (("2d", source.manifest.model_2d), ("3d", source.manifest.model_3d)):
            graph_path = source.path / spec.file
            quantize_graph(graph_path, staging / spec.file, feeds[graph], float_layers(graph_path))
        log(f"quantized both graphs on {len(frames)} calibration frames")
        quantized = Labeler(staging, check_files=False)
        parity = [dataset.load_frame(i, with_labels=False) for i in held_out]
        references = [source.label(f.image, f.points, f.calib) for f in parity]
        matched, reproduced = agreement_on(references, quantized, parity)
        agreement = reproduced / matched if matched else 1.0
        log(f"label parity: {reproduced} of {matched} matched labels reproduced "
            f"({agreement:.1%}; at least {min_agreement:.0%} needed)")  # fmt: skip
        if agreement < min_agreement:
            raise ExportCheckError(
                f"the INT8 version reproduces {agreement:.1%} of version {source.version}'s "
                f"matched labels on {len(held_out)} frames, below the {min_agreement:.0%} "
                "required"
            )
        record = QuantizationRecord(
            scheme=SCHEME, source_version=source.version, calibration_data=str(calibration_data),
            calibration_frames=len(frames), parity_frames=len(held_out),
            matched_labels=matched, reproduced=reproduced, agreement=round(agreement, 4),
            min_agreement=min_agreement,
        )  # fmt: skip

        def write_manifest(name: str) -> None:
            files = dict(source.manifest.files)
            for spec in (source.manifest.model_2d, source.manifest.model_3d):
                files[spec.file] = file_record(staging / spec.file)
            manifest = replace(
                source.manifest, format=3, version=name, files=files, quantization=record,
                exported_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started)),
                retraining=None,
            )  # fmt: skip
            manifest.save(staging)

        name, path = publish(repository, staging, version, finalize=write_manifest)
    log(f"published INT8 version {name} (from {source.version}) at {path}")
    if promote_version:
        promote(repository, name)
    return QuantizeResult(name, path, promote_version, record)
