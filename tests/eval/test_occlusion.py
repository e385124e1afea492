from __future__ import annotations

import numpy as np
import pytest

from detmatch.eval.occlusion import IGNORE_LEVEL, LevelCurve, match_level, object_levels

OBJECTS = np.array([[0, 0, 10, 20], [50, 0, 60, 20], [100, 0, 120, 20]], dtype=float)
LEVELS = np.array([0, 2, IGNORE_LEVEL])  # the third: a DontCare region or a Van
DETECTIONS = np.array(
    [
        [0, 0, 10, 20],  # on the level-0 object
        [50, 1, 60, 21],  # on the level-2 object
        [200, 0, 210, 20],  # on nothing
        [0, 1, 10, 21],  # a duplicate on the level-0 object
        [100, 0, 120, 20],  # on the ignore-only box
    ],
    dtype=float,
)
SCORES = np.array([0.9, 0.8, 0.7, 0.6, 0.95])


def test_a_level_counts_its_own_objects_and_ignores_the_others() -> None:
    scores, hits = match_level(DETECTIONS, SCORES, OBJECTS, LEVELS, 0)
    # The ignore-only box and the level-2 object drop their detections; the duplicate is false.
    assert scores.tolist() == [0.9, 0.7, 0.6] and hits.tolist() == [True, False, False]
    scores, hits = match_level(DETECTIONS, SCORES, OBJECTS, LEVELS, 2)
    # At level 2 the level-0 object is ignored, so its duplicate is dropped too.
    assert scores.tolist() == [0.8, 0.7] and hits.tolist() == [True, False]


def test_a_below_threshold_overlap_is_a_false_positive() -> None:
    shifted = np.array([[5.0, 0, 15, 20]])  # IoU 1/3 with the level-0 object
    scores, hits = match_level(shifted, [0.5], OBJECTS, LEVELS, 0, iou_threshold=0.5)
    assert hits.tolist() == [False]
    scores, hits = match_level(shifted, [0.5], OBJECTS, LEVELS, 0, iou_threshold=0.3)
    assert hits.tolist() == [True]


def test_curve_pools_frames_in_descending_score() -> None:
    curve = LevelCurve()
    curve.add_frame(DETECTIONS, SCORES, OBJECTS, LEVELS, 0)  # 1 of 1 found, 2 false
    curve.add_frame(OBJECTS[:1], [0.99], OBJECTS[:2], np.array([0, 0]), 0)  # 1 of 2 found
    assert curve.objects == 3
    precision, recall = curve.precision_recall()
    # Pooled order: 0.99 hit, 0.9 hit, 0.7 false, 0.6 false.
    np.testing.assert_allclose(precision, [1.0, 1.0, 2 / 3, 0.5])
    np.testing.assert_allclose(recall, [1 / 3, 2 / 3, 2 / 3, 2 / 3])
    # Precision 1 up to recall 2/3, never beyond: 26 of the 40 recall points.
    assert curve.average_precision() == pytest.approx(26 / 40 * 100)


def test_perfect_and_empty_curves() -> None:
    perfect = LevelCurve()
    perfect.add_frame(OBJECTS[:2], [0.9, 0.8], OBJECTS[:2], np.array([1, 1]), 1)
    assert perfect.average_precision() == pytest.approx(100.0)
    empty = LevelCurve()
    empty.add_frame(np.zeros((0, 4)), [], OBJECTS, LEVELS, 1)
    assert empty.objects == 0 and empty.average_precision() == 0.0
    assert len(empty.precision_recall()[0]) == 0


def test_object_levels_ignore_neighbours_dontcare_and_unknown_occlusion() -> None:
    names = np.array(["Car", "Van", "Pedestrian", "DontCare", "car", "Car"])
    occluded = np.array([1, 0, 0, -1, 2, 3])
    rows, levels = object_levels(names, occluded, "Car")
    assert rows.tolist() == [0, 1, 3, 4, 5]
    assert levels.tolist() == [1, IGNORE_LEVEL, IGNORE_LEVEL, 2, IGNORE_LEVEL]
    rows, levels = object_levels(names, occluded, "Pedestrian")
    assert rows.tolist() == [2, 3] and levels.tolist() == [0, IGNORE_LEVEL]
