import itertools
import math
import subprocess
import sys

import numpy as np
import pytest

from detmatch.matching import (
    classification_cost,
    focal_cost,
    hungarian_match,
    l1_cost,
    matching_cost,
)

IMAGE = (1242, 375)


def test_identical_confident_boxes_cost_about_minus_4_8_and_match():
    box = np.array([[100.0, 120.0, 180.0, 200.0]])
    probs = np.array([[0.9, 0.05, 0.05]])
    cost = matching_cost(box, probs, box, probs, IMAGE)
    assert cost[0, 0] == pytest.approx(-4.8, abs=0.05)
    rows, cols = hungarian_match(cost)
    assert rows.tolist() == [0] and cols.tolist() == [0]


def test_identical_unconfident_boxes_do_not_match():
    box = np.array([[100.0, 120.0, 180.0, 200.0]])
    probs = np.array([[0.1, 0.05, 0.05]])
    cost = matching_cost(box, probs, box, probs, IMAGE)
    assert cost[0, 0] > -1.5
    rows, cols = hungarian_match(cost)
    assert rows.size == 0 and cols.size == 0


def direct_focal(p):
    p = min(max(p, 1e-6), 1 - 1e-6)
    return 0.25 * (1 - p) ** 2 * (-math.log(p + 1e-12)) - 0.75 * p**2 * (-math.log(1 - p + 1e-12))


def direct_giou(a, b):
    inter_w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    inter_h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = inter_w * inter_h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    hull = (max(a[2], b[2]) - min(a[0], b[0])) * (max(a[3], b[3]) - min(a[1], b[1]))
    return inter / union - (hull - union) / hull


def random_case(rng, n3, n2, classes=3):
    def boxes(n):
        x1 = rng.uniform(0, 1100, n)
        y1 = rng.uniform(0, 300, n)
        return np.column_stack([x1, y1, x1 + rng.uniform(5, 140, n), y1 + rng.uniform(5, 70, n)])

    def probs(n):
        return rng.dirichlet(np.ones(classes) * 0.5, n) * rng.uniform(0.2, 1.0, (n, 1))

    return boxes(n3), probs(n3), boxes(n2), probs(n2)


@pytest.mark.parametrize("seed", range(5))
def test_every_cost_term_matches_a_direct_transcription(seed):
    rng = np.random.default_rng(seed)
    boxes_3d, probs_3d, boxes_2d, probs_2d = random_case(rng, 5, 4)
    cost = matching_cost(boxes_3d, probs_3d, boxes_2d, probs_2d, IMAGE)
    cls = classification_cost(probs_3d, probs_2d)
    l1 = l1_cost(boxes_3d, boxes_2d, IMAGE)
    width, height = IMAGE
    scale = [width, height, width, height]
    for i, j in itertools.product(range(5), range(4)):
        c3, c2 = int(np.argmax(probs_3d[i])), int(np.argmax(probs_2d[j]))
        expected_cls = direct_focal(probs_3d[i][c2]) + direct_focal(probs_2d[j][c3])
        expected_l1 = 5 * sum(abs(boxes_3d[i][k] - boxes_2d[j][k]) / scale[k] for k in range(4))
        expected_iou = -2 * direct_giou(boxes_3d[i], boxes_2d[j])
        assert cls[i, j] == pytest.approx(expected_cls, rel=1e-9)
        assert l1[i, j] == pytest.approx(expected_l1, rel=1e-9)
        assert cost[i, j] == pytest.approx(expected_cls + expected_l1 + expected_iou, rel=1e-9)


def test_focal_cost_clamps_probabilities():
    assert focal_cost(np.array([0.0, 1.0])) == pytest.approx(
        [direct_focal(1e-6), direct_focal(1 - 1e-6)]
    )


@pytest.mark.parametrize("seed", range(30))
def test_assignment_is_optimal_against_brute_force(seed):
    rng = np.random.default_rng(100 + seed)
    n3, n2 = int(rng.integers(0, 5)), int(rng.integers(0, 5))
    cost = rng.normal(-1.0, 2.0, size=(n3, n2))
    rows, cols = hungarian_match(cost, threshold=np.inf)
    best = math.inf
    small, large = min(n3, n2), max(n3, n2)
    for chosen in itertools.permutations(range(large), small):
        pairs = (
            zip(range(small), chosen, strict=True)
            if n3 <= n2
            else zip(chosen, range(small), strict=True)
        )
        best = min(best, sum(cost[i, j] for i, j in pairs))
    if small == 0:
        assert rows.size == 0
    else:
        assert cost[rows, cols].sum() == pytest.approx(best)
        assert len(set(rows)) == len(rows) == small and len(set(cols)) == len(cols)
    # The threshold only removes assigned pairs, it does not re-assign.
    kept_rows, kept_cols = hungarian_match(cost, threshold=-1.5)
    kept = set(zip(kept_rows.tolist(), kept_cols.tolist(), strict=True))
    assert kept == {
        (i, j) for i, j in zip(rows.tolist(), cols.tolist(), strict=True) if cost[i, j] <= -1.5
    }


def test_empty_inputs_and_bad_input():
    cost = matching_cost(
        np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((2, 4)), np.full((2, 3), 0.3), IMAGE
    )
    assert cost.shape == (0, 2)
    assert [a.size for a in hungarian_match(cost)] == [0, 0]
    with pytest.raises(ValueError, match="classes"):
        classification_cost(np.full((1, 3), 0.5), np.full((1, 2), 0.5))
    with pytest.raises(ValueError, match="NaN"):
        hungarian_match(np.array([[np.nan]]))


def test_matching_imports_no_torch():
    code = "import sys; sys.modules['torch'] = None\nimport detmatch.matching\n"
    subprocess.run([sys.executable, "-c", code], check=True)
