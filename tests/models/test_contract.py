"""Adding a detector is a two-file change: a class implementing the contract, one line in the
builder's mapping. This file is the first file; the test adds the line to the mapping with
monkeypatch. The detector below exists only here: a deliberately small single-scale 3D
detector with one fused output map, unlike PointPillars3D's two heads. It trains through the
supervised and the DetMatch step, exports to ONNX with parity checks, and labels a frame in the
torch-free labeler, through the contract alone."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from commands.main import main
from detmatch.config import Detector3DConfig, load_config
from detmatch.data.augment import CloudTransform
from detmatch.data.dataset import FrameDataset, collate
from detmatch.data.kitti import KittiDataset
from detmatch.geometry import project_boxes_to_image
from detmatch.models import build
from detmatch.models.common import (
    HEATMAP_PRIOR_BIAS,
    draw_gaussian,
    gather_at,
    heatmap_focal_loss,
    heatmap_peaks,
    tensor_like,
)
from detmatch.models.contract import (
    ConsistencyCandidates,
    Decoded,
    Detector3D,
    LabelledArea,
    forward_pillars,
)
from detmatch.models.detector3d import pillar_grid
from detmatch.models.pillars import PILLAR_FEATURES
from detmatch.structures import LabeledBoxes
from detmatch.training.consistency import ConsistencyWeights, consistency_loss
from tests.conftest import REPO

# Fused map channels after the class heatmap: dx, dy, z, log l, log w, log h, yaw.
BOX_CHANNELS = 7


@dataclass(frozen=True)
class TinyTargets:
    heatmap: np.ndarray  # (C, h, w)
    area: np.ndarray  # (1, h, w)
    index: np.ndarray  # (N,)
    boxes: np.ndarray  # (N, 7) the box channels' targets


class TinyPillarNet3D(Detector3D):
    """Pillars -> mean point features per pillar -> BEV canvas -> two convs at stride 2 -> one
    map of C heatmap logits + 7 box channels."""

    consistency_gradient = "the fused map's box channels (single-stage detector)"
    output_names = ("maps",)

    def __init__(self, config: Detector3DConfig, num_classes: int) -> None:
        super().__init__()
        self.config = config
        self.num_classes = num_classes
        self.score_threshold = config.score_threshold
        self.grid = pillar_grid(config)
        width = config.head_width
        self.encode = nn.Linear(PILLAR_FEATURES, width)
        self.body = nn.Sequential(
            nn.Conv2d(width, width, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(width, num_classes + BOX_CHANNELS, 1),
        )
        with torch.no_grad():
            self.body[-1].bias[:num_classes] = HEATMAP_PRIOR_BIAS

    @property
    def cell(self) -> tuple[float, float]:
        return self.config.pillar_size[0] * 2, self.config.pillar_size[1] * 2

    def forward(self, features, coords, counts, batch_size: int = 1):
        ny, nx = self.grid.shape
        valid = torch.arange(features.shape[1], device=features.device)[None] < counts[:, None]
        mean = (features * valid[..., None]).sum(1) / counts.clamp(min=1)[:, None]
        flat = coords[:, 0] * (ny * nx) + coords[:, 1] * nx + coords[:, 2]
        encoded = F.relu(self.encode(mean))
        canvas = encoded.new_zeros(batch_size * ny * nx, encoded.shape[1])
        canvas = canvas.index_put((flat,), encoded)
        canvas = canvas.reshape(batch_size, ny, nx, -1).permute(0, 3, 1, 2)
        return (self.body(canvas),)

    def _boxes(self, pixel: torch.Tensor, values: torch.Tensor, width: int) -> torch.Tensor:
        cell_x, cell_y = self.cell
        x_min, y_min = self.config.point_cloud_range[:2]
        ys = torch.div(pixel, width, rounding_mode="floor")
        xs = pixel - ys * width
        x = (xs.to(values.dtype) + values[..., 0]) * cell_x + x_min
        y = (ys.to(values.dtype) + values[..., 1]) * cell_y + y_min
        dims = torch.exp(values[..., 3:6].clamp(max=4.0))
        return torch.cat([x[..., None], y[..., None], values[..., 2:3], dims, values[..., 6:7]], -1)

    def decode(self, outputs: Sequence[torch.Tensor]) -> Decoded:
        (maps,) = outputs
        heatmap, box = maps[:, : self.num_classes], maps[:, self.num_classes :]
        scores, classes, pixel, probabilities = heatmap_peaks(
            torch.sigmoid(heatmap), self.config.max_detections
        )
        return (
            self._boxes(pixel, gather_at(box, pixel), maps.shape[3]),
            scores,
            classes,
            probabilities,
        )

    def consistency_candidates(self, outputs: Sequence[torch.Tensor]) -> ConsistencyCandidates:
        (maps,) = outputs
        heatmap, box = maps[:, : self.num_classes], maps[:, self.num_classes :]
        scores, _, pixel, probabilities = heatmap_peaks(
            torch.sigmoid(heatmap).detach(), self.config.max_detections
        )
        boxes = self._boxes(pixel, gather_at(box, pixel), maps.shape[3])
        return ConsistencyCandidates(boxes, gather_at(heatmap, pixel), scores, probabilities)

    def build_targets(
        self, labels: LabeledBoxes, view: LabelledArea | None = None, ignore=None
    ) -> TinyTargets:
        ny, nx = self.grid.shape
        h, w = ny // 2, nx // 2
        cell_x, cell_y = self.cell
        x_min, y_min = self.config.point_cloud_range[:2]
        heatmap = np.zeros((self.num_classes, h, w), dtype=np.float32)
        area = np.ones((h, w), dtype=bool)
        if view is not None:
            xs = (np.arange(w) + 0.5) * cell_x + x_min
            ys = (np.arange(h) + 0.5) * cell_y + y_min
            centres = np.stack(np.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
            area = view.contains_bev(centres).reshape(h, w)
        for box in np.zeros((0, 7)) if ignore is None else ignore:  # no background near these
            cx, cy = int((box[0] - x_min) // cell_x), int((box[1] - y_min) // cell_y)
            area[max(cy - 2, 0) : cy + 3, max(cx - 2, 0) : cx + 3] = False
        index, boxes = [], []
        for box, label in zip(labels.boxes, labels.classes, strict=True):
            centre = np.array([(box[0] - x_min) / cell_x, (box[1] - y_min) / cell_y])
            cx, cy = np.floor(centre).astype(int)
            if not (0 <= cx < w and 0 <= cy < h) or np.any(box[3:6] <= 0):
                continue
            draw_gaussian(heatmap[int(label)], cx, cy, 2)
            index.append(cy * w + cx)
            boxes.append([*(centre - (cx, cy)), box[2], *np.log(box[3:6]), box[6]])
        return TinyTargets(
            heatmap, area[None].astype(np.float32), np.asarray(index, dtype=np.int64),
            np.asarray(boxes, dtype=np.float32).reshape(-1, BOX_CHANNELS),
        )  # fmt: skip

    def loss(self, outputs, targets, box_regression: bool = True):
        (maps,) = outputs
        heatmap, box = maps[:, : self.num_classes], maps[:, self.num_classes :]
        target = tensor_like(np.stack([t.heatmap for t in targets]), maps)
        area = tensor_like(np.stack([t.area for t in targets]), maps)
        losses = {"heatmap": heatmap_focal_loss(heatmap, target, area)}
        if box_regression:
            terms = [
                F.l1_loss(box[b].flatten(1)[:, tensor_like(t.index, maps)].t(),
                          tensor_like(t.boxes, maps), reduction="sum")
                for b, t in enumerate(targets) if len(t.index)
            ]  # fmt: skip
            count = max(sum(len(t.index) for t in targets), 1)
            losses["box"] = 0.25 * sum(terms, maps.sum() * 0.0) / count
        return losses


@pytest.fixture
def tiny_registered(monkeypatch):
    """The builder's mapping with the test detector: the second file of the change."""
    monkeypatch.setitem(build.DETECTORS_3D, "tiny-test", TinyPillarNet3D)


def _config_file(tmp_path, synth_root) -> str:
    text = (REPO / "configs" / "tiny.toml").read_text()
    text = text.replace("[detector3d]\n", '[detector3d]\ntype = "tiny-test"\n')
    text = text.replace('root = "data/synth"', f'root = "{synth_root}"')
    path = tmp_path / "tiny_test_detector.toml"
    path.write_text(text)
    return str(path)


def test_an_unknown_detector_type_is_a_config_error(tmp_path, synth_root):
    config = load_config(_config_file(tmp_path, synth_root))
    with pytest.raises(ValueError, match=r"\[detector3d\] type must be one of .*pointpillars"):
        build.build_detectors(config)


def test_a_new_detector_trains_through_both_steps_and_exports(
    tiny_registered, tmp_path, synth_root
):
    from export.onnx_export import export_checkpoint
    from serving.labeler import Labeler

    config_file = _config_file(tmp_path, synth_root)
    pre, ssl, repository = tmp_path / "pre", tmp_path / "dm", tmp_path / "models"
    assert main(["train", "--config", config_file, "--out", str(pre), "--steps", "4"]) == 0
    assert main(["train", "--config", config_file, "--out", str(ssl), "--steps", "2", "--method",
                 "detmatch", "--pretrained", str(pre), "--preset", "paper"]) == 0  # fmt: skip
    records = [json.loads(line) for line in (ssl / "metrics.jsonl").read_text().splitlines()]
    steps = [r for r in records if "consistency" in r]
    assert [r["step"] for r in steps] == [1, 2]
    assert all(math.isfinite(r["loss"]) and r["supervised_3d"] > 0 for r in steps)
    loaded = build.load_detectors(ssl)
    assert isinstance(loaded.model_3d, TinyPillarNet3D)

    result = export_checkpoint(ssl, repository, promote_version=True, synthetic_frames=1,
                               parity_data=[synth_root], parity_frames_per_source=1)  # fmt: skip
    assert result.parity.passed, result.parity.summary()
    assert [o.name for o in Labeler.from_repository(repository).manifest.model_3d.outputs] == [
        "boxes", "scores", "classes", "probabilities", "maps"
    ]  # fmt: skip
    frame = KittiDataset(synth_root).load_frame("000004")
    labels = Labeler.from_repository(repository).label(frame.image, frame.points, frame.calib)
    assert labels.model_version == "000001" and len(labels.detections_3d) > 0


def test_consistency_reaches_a_new_detector_through_its_candidates(synth_root):
    """The consistency loss needs only consistency_candidates: a 2D teacher box at the
    projection of the student's best candidate, shifted, matches it and pulls its box
    channels."""
    config = load_config(REPO / "configs" / "tiny.toml")
    torch.manual_seed(0)
    model = TinyPillarNet3D(config.detector3d, 3)
    dataset = FrameDataset(synth_root, "train", config.data.classes, config.data.image_size,
                           model.grid)  # fmt: skip
    batch = collate([dataset[0]])
    outputs = forward_pillars(model, batch.pillars)
    with torch.no_grad():
        outputs[0][:, :3] = -8.0
        outputs[0][0, 0, 40, 30] = 6.0  # one confident Car peak in front of the sensor
    candidates = model.consistency_candidates(outputs)
    sample = batch.samples[0]
    box = candidates.boxes[0, :1].detach().double().numpy()
    projected = project_boxes_to_image(box, sample.calib, sample.image_transform.original_size)
    teacher = LabeledBoxes(projected + [4.0, -3.0, 6.0, 2.0], np.array([0]),
                           np.array([[0.95, 0.02, 0.03]]))  # fmt: skip
    loss, pairs = consistency_loss(
        model, outputs, [sample], [CloudTransform()], [teacher], ConsistencyWeights(), -1.0
    )
    assert pairs == 1 and loss.item() > 0
    loss.backward()
    assert model.body[-1].weight.grad[3:].abs().sum() > 0  # the box channels
