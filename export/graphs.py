"""The two exported graphs: preprocessing and decoding inside, one frame per call.

2D: the original (H, W, 3) uint8 RGB image of any size -> Cast, Transpose, Resize (linear,
half_pixel: torch's bilinear F.interpolate with align_corners=False and no antialiasing, the
op training's `image_to_tensor` uses) to the config's input size -> CenterNet2D forward
(normalisation included) -> max-pool peaks + top-k decode -> boxes scaled back to the
original image's pixels, as `ImageTransform.invert` does.

3D: `pillarize`'s output for one frame, a dynamic number of pillars P -> PointPillars3D
forward (ScatterND onto the BEV canvas) -> decode to LiDAR-frame boxes.

Both also output their raw head maps, so parity can be checked before decoding.
Exported with torch.onnx's TorchScript exporter (dynamo=False): the torch.export-based
exporter needs the onnxscript package, which the project does not depend on.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
import torch.nn.functional as F
from torch import nn
from torch.onnx.operators import shape_as_tensor

from detmatch.models.contract import Detector2D, Detector3D
from serving.manifest import TensorSpec
from serving.repository import (
    DECODED_OUTPUTS,
    INPUTS_2D,
    INPUTS_3D,
)

OPSET = 17


class ExportCheckError(RuntimeError):
    """An exported graph failed a check (onnx.checker here, parity in export.parity)."""


EXPORTER = "torch.onnx.export (TorchScript exporter, dynamo=False)"


class ImageDetector2DGraph(nn.Module):
    """(H, W, 3) uint8 RGB image -> boxes (K, 4) xyxy pixels of that image, scores (K,),
    classes (K,) int64, probabilities (K, C), and the raw maps heatmap logits (1, C, h, w),
    size (1, 2, h, w), offset (1, 2, h, w)."""

    def __init__(self, detector: Detector2D, input_size: tuple[int, int]) -> None:
        super().__init__()
        self.detector = detector
        self.input_size = (int(input_size[0]), int(input_size[1]))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        width, height = self.input_size
        original = shape_as_tensor(image)[:2].to(torch.float32)
        x = image.permute(2, 0, 1).unsqueeze(0).to(torch.float32)
        x = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)
        maps = self.detector(x)
        boxes, scores, classes, probabilities = self.detector.decode(maps)
        # Input pixels -> original pixels: x * W0 / w, y * H0 / h, clipped to the image as
        # ImageTransform.invert_detections does ([0, W0 - 1] x [0, H0 - 1]).
        scale = torch.stack([original[1] / width, original[0] / height]).repeat(2)
        limit = torch.stack([original[1] - 1, original[0] - 1]).repeat(2)
        boxes = torch.minimum(torch.clamp(boxes[0] * scale, min=0.0), limit)
        return boxes, scores[0], classes[0], probabilities[0], *maps


class PillarDetector3DGraph(nn.Module):
    """features (P, M, 9) float32, coords (P, 2) int64 (iy, ix), num_points (P,) int64 ->
    boxes (K, 7) LiDAR x y z l w h yaw, scores (K,), classes (K,) int64, probabilities (K, C),
    and the detector's raw outputs (batch of 1; PointPillars3D: heatmap logits (1, C, h, w)
    and regression (1, 8, h, w))."""

    def __init__(self, detector: Detector3D) -> None:
        super().__init__()
        self.detector = detector

    def forward(
        self, features: torch.Tensor, coords: torch.Tensor, num_points: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        batch_coords = torch.cat([torch.zeros_like(coords[:, :1]), coords], dim=1)
        maps = self.detector(features, batch_coords, num_points, batch_size=1)
        boxes, scores, classes, probabilities = self.detector.decode(maps)
        return boxes[0], scores[0], classes[0], probabilities[0], *maps


def _export(
    module: nn.Module,
    args: tuple[torch.Tensor, ...],
    path: Path,
    input_names: tuple[str, ...],
    output_names: tuple[str, ...],
    dynamic_axes: dict[str, dict[int, str]],
) -> None:
    module.eval()
    with warnings.catch_warnings():
        # The legacy-exporter notice, and tracer notes about shape values that are constant
        # here (the 2D graph resizes to a fixed size; top-k's k is fixed).
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(
            module,
            args,
            str(path),
            dynamo=False,
            opset_version=OPSET,
            input_names=list(input_names),
            output_names=list(output_names),
            dynamic_axes=dynamic_axes,
            do_constant_folding=True,
        )
    with torch.no_grad():
        outputs = module(*args)
    _declare_output_shapes(
        path, {n: tuple(t.shape) for n, t in zip(output_names, outputs, strict=True)}
    )
    try:
        onnx.checker.check_model(str(path), full_check=True)
    except onnx.checker.ValidationError as error:
        raise ExportCheckError(f"onnx.checker rejects {path.name}: {error}") from None


def _declare_output_shapes(path: Path, shapes: dict[str, tuple[int, ...]]) -> None:
    """Replace the tracer's generated names for output dimensions (e.g. 'Mulboxes_dim_0') by
    their sizes: every output's shape is fixed by the config (K detections, the head maps of
    the fixed input size or pillar grid), whatever the input's size."""
    model = onnx.load(str(path))
    for output in model.graph.output:
        dims = output.type.tensor_type.shape.dim
        for dim, size in zip(dims, shapes[output.name], strict=True):
            dim.Clear()
            dim.dim_value = int(size)
    onnx.save(model, str(path))


def export_detector_2d(
    detector: Detector2D, input_size: tuple[int, int], path: Path, example_image: np.ndarray
) -> None:
    """Write the 2D graph to path (dynamic image height and width) and run onnx.checker."""
    graph = ImageDetector2DGraph(detector, input_size)
    _export(
        graph,
        (torch.from_numpy(np.array(example_image, dtype=np.uint8, copy=True)),),
        path,
        INPUTS_2D,
        DECODED_OUTPUTS + detector.output_names,
        {"image": {0: "height", 1: "width"}},
    )


def export_detector_3d(
    detector: Detector3D,
    path: Path,
    example_pillars: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Write the 3D graph to path (dynamic number of pillars) and run onnx.checker."""
    if len(example_pillars[0]) == 0:
        raise ValueError("the example frame for tracing the 3D graph has no pillars")
    graph = PillarDetector3DGraph(detector)
    _export(
        graph,
        tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in example_pillars),
        path,
        INPUTS_3D,
        DECODED_OUTPUTS + detector.output_names,
        {name: {0: "pillars"} for name in INPUTS_3D},
    )


def io_spec(path: Path) -> dict[str, tuple[TensorSpec, ...]]:
    """Inputs and outputs of an ONNX file: name, dtype, shape (ints, or names of dynamic
    dimensions)."""
    model = onnx.load(str(path), load_external_data=False)

    def describe(values: list[onnx.ValueInfoProto]) -> tuple[TensorSpec, ...]:
        described = []
        for value in values:
            tensor = value.type.tensor_type
            dims = [d.dim_param if d.dim_param else int(d.dim_value) for d in tensor.shape.dim]
            dtype = np.dtype(onnx.helper.tensor_dtype_to_np_dtype(tensor.elem_type)).name
            described.append(TensorSpec(name=value.name, dtype=dtype, shape=tuple(dims)))
        return tuple(described)

    return {"inputs": describe(model.graph.input), "outputs": describe(model.graph.output)}


def opset_of(path: Path) -> int:
    model = onnx.load(str(path), load_external_data=False)
    return max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
