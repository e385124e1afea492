import math

import numpy as np
import pytest
import torch

from detmatch.config import load_config
from detmatch.data.dataset import collate_pillars
from detmatch.models.common import heatmap_peaks
from detmatch.models.contract import forward_pillars
from detmatch.models.detector2d import CenterNet2D
from detmatch.models.detector3d import PointPillars3D
from detmatch.models.pillars import PillarGrid, batch_pillars, pillarize
from detmatch.structures import LabeledBoxes
from export.graphs import PillarDetector3DGraph
from tests.conftest import REPO

TINY = load_config(REPO / "configs" / "tiny.toml")
NUM_CLASSES = len(TINY.data.classes)


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


@pytest.fixture
def detector_2d():
    torch.manual_seed(0)
    return CenterNet2D(TINY.detector2d, NUM_CLASSES)


@pytest.fixture
def detector_3d():
    torch.manual_seed(0)
    return PointPillars3D(TINY.detector3d, NUM_CLASSES)


def test_2d_forward_backward_and_shapes(detector_2d):
    width, height = TINY.data.image_size
    images = torch.rand(2, 3, height, width) * 255
    heatmap, size, offset = detector_2d(images)
    assert heatmap.shape == (2, NUM_CLASSES, height // 4, width // 4)
    assert size.shape == offset.shape == (2, 2, height // 4, width // 4)
    targets = [
        detector_2d.build_targets(
            LabeledBoxes(np.array([[40.0, 20.0, 90.0, 60.0]]), np.array([0])), (width, height)
        ),
        detector_2d.build_targets(LabeledBoxes.empty(4), (width, height)),
    ]
    losses = detector_2d.loss((heatmap, size, offset), targets)
    sum(losses.values()).backward()
    assert all(torch.isfinite(v) for v in losses.values())
    assert all(p.grad is not None for p in detector_2d.parameters() if p.requires_grad)
    with torch.no_grad():
        boxes, scores, classes, probabilities = detector_2d.eval().decode(detector_2d(images))
    k = TINY.detector2d.max_detections
    assert boxes.shape == (2, k, 4) and scores.shape == classes.shape == (2, k)
    assert probabilities.shape == (2, k, NUM_CLASSES)
    # The score of a detection is its class's entry in the probability vector.
    np.testing.assert_allclose(probabilities.gather(2, classes[..., None])[..., 0], scores)


def test_2d_decoding_recovers_a_box_from_hand_set_heads(detector_2d):
    width, height = TINY.data.image_size
    box = np.array([[101.0, 30.5, 161.0, 70.5]])
    target = detector_2d.build_targets(LabeledBoxes(box, np.array([2])), (width, height))
    out_w = width // 4
    heatmap = torch.from_numpy(logit(target.heatmap))[None]
    size = torch.zeros(1, 2, height // 4, out_w)
    offset = torch.zeros(1, 2, height // 4, out_w)
    cell_y, cell_x = divmod(int(target.index[0]), out_w)
    size[0, :, cell_y, cell_x] = torch.from_numpy(target.size[0])
    offset[0, :, cell_y, cell_x] = torch.from_numpy(target.offset[0])
    boxes, scores, classes, probabilities = detector_2d.decode((heatmap, size, offset))
    assert classes[0, 0] == 2 and scores[0, 0] == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(boxes[0, 0].numpy(), box[0], atol=1e-4)
    assert scores[0, 1] < 0.5  # one object, one peak


def test_3d_forward_backward_and_shapes(detector_3d):
    rng = np.random.default_rng(0)
    points = np.concatenate(
        [rng.uniform([0, -25, -2], [50, 25, 0.5], size=(4000, 3)), rng.uniform(0, 1, (4000, 1))],
        axis=1,
    ).astype(np.float32)
    pillars = pillarize(points, detector_3d.grid)
    heatmap, regression = forward_pillars(detector_3d, collate_pillars([pillars]))
    out_h, out_w = detector_3d.output_shape
    assert heatmap.shape == (1, NUM_CLASSES, out_h, out_w)
    assert regression.shape == (1, 8, out_h, out_w)
    target = detector_3d.build_targets(
        LabeledBoxes(np.array([[20.0, 3.0, -0.9, 3.9, 1.6, 1.5, 0.4]]), np.array([0]))
    )
    losses = detector_3d.loss((heatmap, regression), [target])
    sum(losses.values()).backward()
    assert all(torch.isfinite(v) for v in losses.values())
    assert all(p.grad is not None for p in detector_3d.parameters())
    with torch.no_grad():
        boxes, scores, classes, probabilities, *_ = PillarDetector3DGraph(detector_3d.eval())(
            *(torch.from_numpy(a) for a in batch_pillars([pillars]))
        )
    k = TINY.detector3d.max_detections
    assert boxes.shape == (1, k, 7) and probabilities.shape == (1, k, NUM_CLASSES)


def test_3d_decoding_recovers_a_box_from_hand_set_heads(detector_3d):
    box = np.array([[23.7, -4.2, -0.85, 3.9, 1.6, 1.52, 2.5]])
    target = detector_3d.build_targets(LabeledBoxes(box, np.array([1])))
    out_h, out_w = detector_3d.output_shape
    heatmap = torch.from_numpy(logit(target.heatmap))[None]
    regression = torch.zeros(1, 8, out_h, out_w)
    cell_y, cell_x = divmod(int(target.index[0]), out_w)
    regression[0, :, cell_y, cell_x] = torch.from_numpy(target.regression[0])
    boxes, scores, classes, _ = detector_3d.decode((heatmap, regression))
    assert classes[0, 0] == 1 and scores[0, 0] == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(boxes[0, 0, :6].numpy(), box[0, :6], atol=1e-4)
    assert math.remainder(float(boxes[0, 0, 6]) - box[0, 6], 2 * math.pi) == pytest.approx(
        0.0, abs=1e-5
    )


def test_heatmap_peaks_suppress_neighbours_and_keep_probability_vectors():
    heat = torch.zeros(1, 2, 5, 5)
    heat[0, 0, 2, 2], heat[0, 0, 2, 3], heat[0, 1, 2, 2] = 0.9, 0.8, 0.3
    scores, classes, pixel, probabilities = heatmap_peaks(heat, 2)
    assert scores[0].tolist() == pytest.approx([0.9, 0.3])  # 0.8 is not a local maximum
    assert classes[0].tolist() == [0, 1] and pixel[0].tolist() == [12, 12]
    assert probabilities[0, 0].tolist() == pytest.approx([0.9, 0.3])


def test_pillarize_keeps_points_and_features():
    grid = PointPillars3D(TINY.detector3d, NUM_CLASSES).grid
    points = np.array(
        [
            [1.3, 0.1, -1.0, 0.5],
            [1.5, 0.3, -0.5, 0.7],
            [10.0, -5.0, 0.0, 0.1],
            [-3.0, 0.0, 0.0, 0.0],
        ],
        dtype=np.float32,
    )
    features, coords, counts = pillarize(points, grid).arrays
    assert sorted(counts.tolist()) == [1, 2]
    assert counts.sum() == 3  # the point behind the sensor is outside the range
    first = int(np.argmax(counts))
    pillar = features[first, :2]
    np.testing.assert_allclose(pillar[:, :4], points[:2], atol=1e-6)
    np.testing.assert_allclose(pillar[:, 4:7].sum(axis=0), 0.0, atol=1e-6)  # offsets to the mean
    x_min, y_min = grid.point_cloud_range[:2]
    centre = (coords[first, ::-1] + 0.5) * np.array(grid.pillar_size) + [x_min, y_min]
    np.testing.assert_allclose(pillar[:, 7:9], points[:2, :2] - centre, atol=1e-5)
    assert np.all(features[first, 2:] == 0)


def _reference_pillars(points: np.ndarray, grid: PillarGrid) -> tuple[np.ndarray, ...]:
    """pillarize's contract written plainly, one pillar at a time, with the same float32 /
    float64 arithmetic: what the vectorised version must reproduce bit for bit."""
    x_min, y_min, z_min, x_max, y_max, z_max = grid.point_cloud_range
    ny, nx = grid.shape
    cells: dict[int, list[int]] = {}
    for i, (x, y, z, _) in enumerate(points):
        if x_min <= x < x_max and y_min <= y < y_max and z_min <= z < z_max:
            ix = min(
                max(int(np.float32(x - np.float32(x_min)) / np.float32(grid.pillar_size[0])), 0),
                nx - 1,
            )
            iy = min(
                max(int(np.float32(y - np.float32(y_min)) / np.float32(grid.pillar_size[1])), 0),
                ny - 1,
            )
            cells.setdefault(iy * nx + ix, []).append(i)  # input order within a pillar
    occupied = sorted(cells)
    if len(occupied) > grid.max_pillars:  # the fullest, ties to the lower cell; then cell order
        fullest = sorted(occupied, key=lambda c: (-len(cells[c]), c))[: grid.max_pillars]
        occupied = sorted(fullest)
    m = grid.max_points_per_pillar
    features = np.zeros((len(occupied), m, 9), dtype=np.float32)
    coords = np.array([[c // nx, c % nx] for c in occupied], dtype=np.int64).reshape(-1, 2)
    counts = np.array([min(len(cells[c]), m) for c in occupied], dtype=np.int64)
    for p, cell in enumerate(occupied):
        kept = points[cells[cell][:m]]
        mean = (kept[:, :3].astype(np.float64).sum(axis=0) / len(kept)).astype(np.float32)
        centre_x = (np.float32(cell % nx) + np.float32(0.5)) * np.float32(grid.pillar_size[0])
        centre_y = (np.float32(cell // nx) + np.float32(0.5)) * np.float32(grid.pillar_size[1])
        features[p, : len(kept), :4] = kept
        features[p, : len(kept), 4:7] = kept[:, :3] - mean
        features[p, : len(kept), 7] = kept[:, 0] - (centre_x + np.float32(x_min))
        features[p, : len(kept), 8] = kept[:, 1] - (centre_y + np.float32(y_min))
    return features, coords, counts


@pytest.mark.parametrize("max_pillars", [20_000, 150])
def test_pillarize_matches_its_contract_bit_for_bit(max_pillars):
    """Crowded pillars (more points than max_points_per_pillar), points outside the range on
    every side, and more occupied pillars than max_pillars."""
    rng = np.random.default_rng(3)
    tiny = PointPillars3D(TINY.detector3d, NUM_CLASSES).grid
    grid = PillarGrid(tiny.point_cloud_range, tiny.pillar_size, tiny.max_points_per_pillar,
                      max_pillars)  # fmt: skip
    x_min, y_min, z_min, x_max, y_max, z_max = grid.point_cloud_range
    spread = rng.uniform([x_min - 5, y_min - 5, z_min - 1, 0], [x_max + 5, y_max + 5, z_max + 1, 1],
                         size=(3000, 4))  # fmt: skip
    crowd = rng.normal([10.0, 2.0, -1.0, 0.5], [0.3, 0.3, 0.5, 0.1], size=(400, 4))
    points = np.concatenate([spread, crowd])[rng.permutation(3400)].astype(np.float32)
    expected = _reference_pillars(points, grid)
    got = pillarize(points, grid).arrays
    assert got[2].max() == grid.max_points_per_pillar  # some pillars were cut
    for mine, theirs in zip(got, expected, strict=True):
        assert mine.dtype == theirs.dtype and mine.shape == theirs.shape
        assert np.array_equal(mine, theirs)


def test_a_padded_batch_of_pillars_gives_each_frame_its_own_outputs(detector_3d):
    """batch_pillars pads a frame by repeating its last pillar and gives an empty frame one
    zero-point pillar: through the graph every frame's heads equal its own batch of one."""
    rng = np.random.default_rng(3)
    clouds = [
        np.column_stack([rng.uniform(0, 40, (n, 1)), rng.uniform(-15, 15, (n, 1)),
                         rng.uniform(-2, 0.5, (n, 1)), rng.uniform(0, 1, (n, 1))])
        .astype(np.float32)
        for n in (900, 40)
    ] + [np.zeros((0, 4), np.float32)]  # fmt: skip
    frames = [pillarize(c, detector_3d.grid) for c in clouds]
    features, coords, counts = batch_pillars(frames)
    widest = max(len(f) for f in frames)
    assert features.shape[:2] == coords.shape[:2] == counts.shape == (3, widest)
    assert (coords[1, len(frames[1]) :] == frames[1].coords[-1]).all()
    assert (counts[2] == 0).all() and (coords[2] == 0).all() and not features[2].any()
    single = batch_pillars(frames[:1])
    assert np.shares_memory(single[0], frames[0].features) and single[0].shape[0] == 1
    graph = PillarDetector3DGraph(detector_3d.eval())
    with torch.no_grad():
        together = graph(*(torch.from_numpy(a) for a in (features, coords, counts)))
        for i, frame in enumerate(frames):
            alone = graph(*(torch.from_numpy(a) for a in batch_pillars([frame])))
            for got, expected in zip(together[4:], alone[4:], strict=True):  # the raw heads
                torch.testing.assert_close(got[i : i + 1], expected, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="no frames"):
        batch_pillars([])


def test_3d_detector_handles_an_empty_point_cloud(detector_3d):
    pillars = pillarize(np.zeros((0, 4), dtype=np.float32), detector_3d.grid)
    assert pillars.features.shape == (0, TINY.detector3d.max_points_per_pillar, 9)
    with torch.no_grad():
        boxes, scores, *_ = PillarDetector3DGraph(detector_3d.eval())(
            *(torch.from_numpy(a[None]) for a in pillars.arrays)
        )
    assert boxes.shape == (1, TINY.detector3d.max_detections, 7) and torch.isfinite(scores).all()


def test_pillar_encoder_training_path_equals_the_padded_layout(detector_3d):
    """Training runs the encoder on real points only; it must compute what the padded layout
    (inference, export) computes in training mode: outputs, gradients and BatchNorm's running
    statistics, which include the padding slots. Both are compared with a float64 reference."""
    import copy

    rng = np.random.default_rng(1)
    points = np.concatenate(
        [rng.uniform([0, -25, -2], [50, 25, 0.5], size=(6000, 3)), rng.uniform(0, 1, (6000, 1))],
        axis=1,
    ).astype(np.float32)
    pillars = collate_pillars([pillarize(points, detector_3d.grid)] * 2)
    assert int(pillars.counts.sum()) < 0.5 * pillars.features.shape[0] * pillars.features.shape[1]
    encoder = detector_3d.encoder.train()
    with torch.no_grad():
        encoder.norm.weight.uniform_(0.5, 1.5)
        encoder.norm.bias.uniform_(-0.5, 0.5)
    reference = copy.deepcopy(encoder).double()
    points_path = copy.deepcopy(encoder)
    expected = reference._forward_padded(pillars.features.double(), pillars.counts)
    expected.sum().backward()
    got = points_path(pillars.features, pillars.counts)  # training mode: the points path
    got.sum().backward()
    np.testing.assert_allclose(got.detach().double(), expected.detach(), rtol=1e-4, atol=1e-4)
    for name in ("linear.weight", "norm.weight", "norm.bias"):
        grad = dict(points_path.named_parameters())[name].grad.double()
        want = dict(reference.named_parameters())[name].grad
        np.testing.assert_allclose(grad, want, rtol=1e-3, atol=1e-3 * float(want.abs().max()))
    for name in ("running_mean", "running_var"):
        np.testing.assert_allclose(
            getattr(points_path.norm, name).double(), getattr(reference.norm, name), rtol=1e-4
        )
    assert int(points_path.norm.num_batches_tracked) == 1
    # Inference takes the padded layout: the eval-mode result of the same weights agrees.
    points_path.eval()
    reference.eval()
    np.testing.assert_allclose(
        points_path(pillars.features, pillars.counts).detach().double(),
        reference(pillars.features.double(), pillars.counts).detach(),
        rtol=1e-4, atol=1e-4,
    )  # fmt: skip


def test_the_heatmap_loss_is_averaged_over_peaks():
    from detmatch.models.common import heatmap_focal_loss

    logits = torch.full((1, 2, 6, 6), -1.0)
    target = torch.zeros(1, 2, 6, 6)
    target[0, 0, 2, 2] = 1.0
    one_peak = heatmap_focal_loss(logits, target)
    target[0, 1, 4, 4] = 1.0
    two_peaks = heatmap_focal_loss(logits, target)
    # Each peak adds the same positive term; the sum is divided by the number of peaks.
    assert two_peaks.item() < one_peak.item()
    assert heatmap_focal_loss(logits, torch.zeros_like(target)).item() > 0  # no peak: over 1


def test_ignore_regions_learn_no_background(detector_2d, detector_3d):
    """An uncertain object's surroundings are left out of the heatmap loss's background term:
    a confident prediction there costs nothing, while the same prediction elsewhere does."""
    from detmatch.models.common import heatmap_focal_loss

    pedestrian = np.array([[20.0, 3.0, -0.8, 0.6, 0.6, 1.8, 0.0]])
    none_3d = LabeledBoxes.empty(7)
    free = detector_3d.build_targets(none_3d)
    ignored = detector_3d.build_targets(none_3d, ignore=pedestrian)
    assert free.labelled_area.all() and not ignored.heatmap.any()
    x, y = detector_3d._centre_cell(pedestrian[0])[1]
    hole = np.argwhere(ignored.labelled_area[0] == 0)
    assert [y, x] in hole.tolist() and len(hole) == 25  # the 5 x 5 square of a radius-2 label
    outside = pedestrian + [200.0, 0, 0, 0, 0, 0, 0]  # beyond the grid: ignores nothing
    assert detector_3d.build_targets(none_3d, ignore=outside).labelled_area.all()

    logits = torch.full((1, NUM_CLASSES, *free.heatmap.shape[1:]), -8.0)
    logits[0, 1, y, x] = 4.0  # a confident pedestrian where the teacher saw one
    target = torch.zeros_like(logits)
    cost = [
        heatmap_focal_loss(logits, target, torch.from_numpy(t.labelled_area[None])).item()
        for t in (free, ignored)
    ]
    assert cost[0] > 1.0 and cost[1] < 1e-3

    width, height = TINY.data.image_size
    rider = np.array([[40.0, 20.0, 60.0, 70.0]])
    far_left = np.array([[-90.0, 0.0, -50.0, 40.0]])  # off the image: ignores nothing
    targets_2d = detector_2d.build_targets(LabeledBoxes.empty(4), (width, height), rider)
    area = targets_2d.labelled_area[0]
    assert area[5:18, 10:15].sum() == 0 and area.sum() == area.size - 13 * 5
    off = detector_2d.build_targets(LabeledBoxes.empty(4), (width, height), far_left)
    assert off.labelled_area.all()
