"""The 3D detector's light second stage (detmatch.models.refine): residuals, training, where the
consistency gradient goes, and export."""

import dataclasses

import numpy as np
import pytest
import torch

from detmatch.config import load_config
from detmatch.data.augment import CloudTransform
from detmatch.data.dataset import FrameDataset, collate
from detmatch.geometry import project_boxes_to_image
from detmatch.models.build import build_detectors
from detmatch.models.contract import forward_pillars
from detmatch.models.refine import apply_residual, nearest_labels, residual_targets
from detmatch.structures import LabeledBoxes
from detmatch.training.consistency import ConsistencyWeights, consistency_loss
from detmatch.training.semi_supervised import load_pretrained
from tests.conftest import REPO

TINY = load_config(REPO / "configs" / "tiny.toml")


def test_residuals_round_trip():
    rng = np.random.default_rng(0)
    rois = np.column_stack([rng.uniform(0, 40, 20), rng.uniform(-10, 10, 20),
                            rng.uniform(-2, 0, 20), rng.uniform(0.5, 5, (20, 3)),
                            rng.uniform(-np.pi, np.pi, 20)])  # fmt: skip
    truth = rois + rng.normal(0, 0.2, rois.shape)
    truth[:, 3:6] = np.abs(truth[:, 3:6])
    residual = residual_targets(rois, truth)
    back = apply_residual(torch.from_numpy(rois), torch.from_numpy(residual).double()).numpy()
    np.testing.assert_allclose(back[:, :6], truth[:, :6], atol=1e-4)
    assert np.abs((back[:, 6] - truth[:, 6] + np.pi) % (2 * np.pi) - np.pi).max() < 1e-4
    assert nearest_labels(rois[:2], truth).tolist() == [0, 1]
    assert nearest_labels(rois[:2] + [50, 0, 0, 0, 0, 0, 0], truth).tolist() == [-1, -1]


@pytest.fixture
def refining(synth_root):
    config = TINY.replace("detector3d", refine=True).replace("data", root=str(synth_root))
    torch.manual_seed(0)
    _, model = build_detectors(config)
    dataset = FrameDataset(synth_root, "train", config.data.classes, config.data.image_size,
                           model.grid)  # fmt: skip
    return model, collate([dataset[0], dataset[1]])


def test_a_fresh_refinement_returns_the_dense_boxes_and_learns(refining):
    model, batch = refining
    assert model.output_names == ("heatmap", "regression", "bev_features")
    outputs = forward_pillars(model.train(), batch.pillars)
    plain = dataclasses.replace(model.config, refine=False)
    dense = type(model)(plain, model.num_classes)
    dense.load_state_dict({k: v for k, v in model.state_dict().items()
                           if not k.startswith("refinement.")})  # fmt: skip
    assert torch.allclose(model.decode(outputs)[0], dense.decode(outputs[:2])[0], atol=1e-5)
    targets = [model.build_targets(s.gt_3d) for s in batch.samples]
    losses = model.loss(outputs, targets)
    assert set(losses) == {"heatmap", "regression", "refine"} and losses["refine"] > 0
    losses["refine"].backward()
    assert model.refinement.mlp[-1].weight.grad.abs().sum() > 0
    assert model.regression_head[-1].weight.grad is None  # the residuals see detached boxes


def _pull(model, batch) -> None:
    """The consistency box terms against a 2D target offset from the best candidate."""
    outputs = forward_pillars(model.train(), batch.pillars)
    with torch.no_grad():
        outputs[0][:, :] = -8.0
        outputs[0][0, 0, 40, 30] = 6.0
    candidates = model.consistency_candidates(outputs)
    sample = batch.samples[0]
    box = candidates.boxes[0, :1].detach().double().numpy()
    projected = project_boxes_to_image(box, sample.calib, sample.image_transform.original_size)
    target = LabeledBoxes(projected + [3.0, -2.0, 5.0, 2.0], np.array([0]),
                          np.array([[0.95, 0.02, 0.03]]))  # fmt: skip
    samples, clouds = [sample, batch.samples[1]], [CloudTransform()] * 2
    weights = ConsistencyWeights(use_class=False)
    loss, pairs = consistency_loss(model, outputs, samples, clouds, [target] * 2, weights, -1.0)
    assert pairs >= 1
    loss.backward()


def test_the_consistency_gradient_reaches_only_the_second_stage(refining, synth_root):
    model, batch = refining
    _pull(model, batch)
    assert model.regression_head[-1].weight.grad is None
    assert model.refinement.mlp[0].weight.grad is not None
    assert "second stage" in model.consistency_gradient
    config = TINY.replace("data", root=str(synth_root))
    torch.manual_seed(0)
    _, single = build_detectors(config)
    _pull(single, batch)
    assert single.regression_head[-1].weight.grad.abs().sum() > 0


def test_a_refining_detector_exports_with_parity(synth_root, tmp_path):
    """The second stage (grid_sample, the residual MLP) is in the exported graph and agrees
    with PyTorch; the labeler serves refined boxes."""
    from detmatch.config import config_to_dict
    from detmatch.training.checkpoint import save_checkpoint
    from export.onnx_export import export_checkpoint
    from serving.labeler import Labeler

    config = TINY.replace("detector3d", refine=True).replace("data", root=str(synth_root))
    torch.manual_seed(0)
    model_2d, model_3d = build_detectors(config)
    with torch.no_grad():  # a refinement that moves boxes, so parity checks it
        model_3d.refinement.mlp[-1].weight.normal_(0, 0.01)
    checkpoint = tmp_path / "run" / "checkpoints" / "step_00000001.pt"
    save_checkpoint(checkpoint, {"format": 1, "step": 1, "config": config_to_dict(config),
                                 "model_2d": model_2d.state_dict(),
                                 "model_3d": model_3d.state_dict(), "metrics": {}})  # fmt: skip
    result = export_checkpoint(tmp_path / "run", tmp_path / "models", promote_version=True,
                               synthetic_frames=1, parity_data=[synth_root],
                               parity_frames_per_source=1)  # fmt: skip
    assert result.parity.passed, result.parity.summary()
    labeler = Labeler.from_repository(tmp_path / "models")
    assert [o.name for o in labeler.manifest.model_3d.outputs][-1] == "bev_features"


def test_a_single_stage_pretraining_loads_into_a_refining_detector(refining):
    """Teacher-student runs may add the second stage to a single-stage pre-training: the
    refinement starts fresh (the dense boxes unchanged); any other missing weight is an error."""
    model, batch = refining
    plain = type(model)(dataclasses.replace(model.config, refine=False), model.num_classes)
    torch.manual_seed(1)
    for parameter in plain.parameters():
        parameter.data.normal_(0, 0.05)
    fresh = load_pretrained(model, plain.state_dict())
    assert fresh and all(k.startswith("refinement.") for k in fresh)
    outputs = forward_pillars(model.eval(), batch.pillars)
    expected = plain.eval().decode(forward_pillars(plain, batch.pillars))[0]
    assert torch.allclose(model.decode(outputs)[0], expected, atol=1e-5)
    broken = {k: v for k, v in plain.state_dict().items() if not k.startswith("neck.")}
    with pytest.raises(RuntimeError, match="neck"):
        load_pretrained(model, broken)
