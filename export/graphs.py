"""The two exported graphs: preprocessing and decoding inside, a batch of frames per call.

Every input and output has a leading batch axis ("batch", dynamic), as Triton's dynamic
batcher and the service's (serving.batching) expect; one frame is a batch of 1.

2D: B original (H, W, 3) uint8 RGB images of one size -> Cast, Transpose, Resize (linear,
half_pixel: torch's bilinear F.interpolate with align_corners=False and no antialiasing, the
op training's `image_to_tensor` uses) to the config's input size -> CenterNet2D forward
(normalisation included) -> max-pool peaks + top-k decode -> boxes scaled back to the
original image's pixels, as `ImageTransform.invert` does.

3D: `pillarize`'s output for B frames, padded to one number of pillars P (dynamic): a frame
with fewer pillars repeats its last pillar, which scatters the same feature onto the same
cell again (`serving.labeler.batch_pillars`) -> PointPillars3D forward (ScatterND onto B BEV
canvases) -> decode to LiDAR-frame boxes.

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
from detmatch.models.pillars import Pillars, batch_pillars
from serving.manifest import TensorSpec
from serving.repository import (
    BATCH_AXIS,
    DECODED_OUTPUTS,
    INPUTS_2D,
    INPUTS_3D,
)

OPSET = 17


class ExportCheckError(RuntimeError):
    """An exported graph failed a check (onnx.checker here, parity in export.parity)."""


EXPORTER = "torch.onnx.export (TorchScript exporter, dynamo=False)"


class ImageDetector2DGraph(nn.Module):
    """(B, H, W, 3) uint8 RGB images -> boxes (B, K, 4) xyxy pixels of the images, scores
    (B, K), classes (B, K) int64, probabilities (B, K, C), and the raw maps heatmap logits
    (B, C, h, w), size (B, 2, h, w), offset (B, 2, h, w)."""

    def __init__(self, detector: Detector2D, input_size: tuple[int, int]) -> None:
        super().__init__()
        self.detector = detector
        self.input_size = (int(input_size[0]), int(input_size[1]))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        width, height = self.input_size
        original = shape_as_tensor(image)[1:3].to(torch.float32)
        x = image.permute(0, 3, 1, 2).to(torch.float32)
        x = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)
        maps = self.detector(x)
        boxes, scores, classes, probabilities = self.detector.decode(maps)
        # Input pixels -> original pixels: x * W0 / w, y * H0 / h, clipped to the image as
        # ImageTransform.invert_detections does ([0, W0 - 1] x [0, H0 - 1]).
        scale = torch.stack([original[1] / width, original[0] / height]).repeat(2)
        limit = torch.stack([original[1] - 1, original[0] - 1]).repeat(2)
        boxes = torch.minimum(torch.clamp(boxes * scale, min=0.0), limit)
        return boxes, scores, classes, probabilities, *maps


class PillarDetector3DGraph(nn.Module):
    """features (B, P, M, 9) float32, coords (B, P, 2) int64 (iy, ix), num_points (B, P)
    int64 -> boxes (B, K, 7) LiDAR x y z l w h yaw, scores (B, K), classes (B, K) int64,
    probabilities (B, K, C), and the detector's raw outputs (PointPillars3D: heatmap logits
    (B, C, h, w) and regression (B, 8, h, w))."""

    def __init__(self, detector: Detector3D) -> None:
        super().__init__()
        self.detector = detector

    def forward(
        self, features: torch.Tensor, coords: torch.Tensor, num_points: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        batch, pillars = features.shape[0], features.shape[1]
        frame = torch.arange(batch, dtype=coords.dtype).reshape(-1, 1, 1).expand(-1, pillars, 1)
        batch_coords = torch.cat([frame, coords], dim=2).reshape(-1, 3)
        maps = self.detector(
            features.flatten(0, 1), batch_coords, num_points.flatten(), batch_size=batch
        )
        boxes, scores, classes, probabilities = self.detector.decode(maps)
        return boxes, scores, classes, probabilities, *maps


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
    """Replace the tracer's generated names for output dimensions (e.g. 'Mulboxes_dim_0'):
    the first is the batch axis, "batch"; every other is fixed by the config (K detections,
    the head maps of the fixed input size or pillar grid), whatever the input's size."""
    model = onnx.load(str(path))
    for output in model.graph.output:
        dims = output.type.tensor_type.shape.dim
        for axis, (dim, size) in enumerate(zip(dims, shapes[output.name], strict=True)):
            dim.Clear()
            if axis == 0:
                dim.dim_param = BATCH_AXIS
            else:
                dim.dim_value = int(size)
    onnx.save(model, str(path))


def export_detector_2d(
    detector: Detector2D, input_size: tuple[int, int], path: Path, example_image: np.ndarray
) -> None:
    """Write the 2D graph to path (dynamic batch, image height and width) and run
    onnx.checker. Traced on a batch of two (the example and its mirror image), so that no
    size-1 batch axis is taken for a constant."""
    graph = ImageDetector2DGraph(detector, input_size)
    image = np.asarray(example_image, dtype=np.uint8)
    _export(
        graph,
        (torch.from_numpy(np.stack([image, image[:, ::-1]])),),
        path,
        INPUTS_2D,
        DECODED_OUTPUTS + detector.output_names,
        {"image": {0: BATCH_AXIS, 1: "height", 2: "width"}},
    )


def export_detector_3d(
    detector: Detector3D,
    path: Path,
    example_pillars: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Write the 3D graph to path (dynamic batch and number of pillars) and run
    onnx.checker. Traced on a batch of two: the example frame, and the example frame with
    only its first half of pillars (padded as `batch_pillars` pads)."""
    if len(example_pillars[0]) == 0:
        raise ValueError("the example frame for tracing the 3D graph has no pillars")
    whole = Pillars(*example_pillars)
    half = Pillars(*(a[: max(1, len(whole) // 2)] for a in example_pillars))
    _export(
        PillarDetector3DGraph(detector),
        tuple(torch.from_numpy(a) for a in batch_pillars([whole, half])),
        path,
        INPUTS_3D,
        DECODED_OUTPUTS + detector.output_names,
        {"features": {0: BATCH_AXIS, 1: "pillars"}, "coords": {0: BATCH_AXIS, 1: "pillars"},
         "num_points": {0: BATCH_AXIS, 1: "pillars"}},
    )  # fmt: skip


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
