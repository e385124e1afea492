"""benchmarks/pseudo_label_sweep.py: confidence thresholding's labels at one threshold and the
equal-recall comparison (no detectors here)."""

import numpy as np

from benchmarks.pseudo_label_sweep import at_equal_recall, confidence_rows
from detmatch.structures import Detections

CLASSES = ("Car", "Pedestrian", "Cyclist")


def detections(boxes, probabilities) -> Detections:
    probabilities = np.array(probabilities)
    return Detections(np.array(boxes, dtype=float), probabilities.max(1),
                      probabilities.argmax(1), probabilities)  # fmt: skip


def test_confidence_rows_keep_each_modality_above_the_threshold_in_its_own_box_column():
    det_2d = detections([[10, 10, 50, 40], [60, 10, 80, 60]], [[0.9, 0.05, 0.05], [0.2, 0.4, 0.4]])
    det_3d = detections(
        [[10, 0, -1, 4, 1.7, 1.5, 0], [8, 2, -1, 0.6, 0.6, 1.8, 0]],
        [[0.3, 0.6, 0.1], [0.1, 0.1, 0.8]],
    )

    rows = confidence_rows(det_2d, det_3d, 0.5, CLASSES)

    in_3d = rows.boxes_3d.data.any(axis=1)
    assert sorted(rows.names[in_3d]) == ["Cyclist", "Pedestrian"]
    assert list(rows.names[~in_3d]) == ["Car"]
    np.testing.assert_array_equal(rows.boxes_2d.xyxy[~in_3d], [[10, 10, 50, 40]])
    assert not rows.boxes_2d.xyxy[in_3d].any()
    assert len(confidence_rows(det_2d, det_3d, 0.95, CLASSES)) == 0


def test_equal_recall_takes_the_most_precise_threshold_that_still_reaches_the_recall():
    sweep = {
        0.3: {"precision": 0.5, "recall": 0.8},
        0.4: {"precision": 0.75, "recall": 0.7},
        0.5: {"precision": 0.7, "recall": 0.6},
        0.6: {"precision": 0.7, "recall": 0.6},
        0.7: {"precision": 0.9, "recall": 0.2},
    }

    assert at_equal_recall(sweep, 0.6) == (0.4, sweep[0.4])  # not the stricter, less precise 0.5
    assert at_equal_recall(sweep, 0.71) == (0.3, sweep[0.3])
    assert at_equal_recall(sweep, 0.1) == (0.7, sweep[0.7])
    assert at_equal_recall(sweep, 0.9) is None
    del sweep[0.4]
    assert at_equal_recall(sweep, 0.6) == (0.6, sweep[0.6])  # the strictest of equals
