import numpy as np
import pytest

from detmatch.eval.pseudo_labels import pooled_precision_recall_f1, pseudo_label_quality
from detmatch.geometry import pairwise_iou_2d, pairwise_iou_3d
from detmatch.structures import Boxes2D, Boxes3D, Labels

IOU_3D = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
IOU_2D = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}


def labels(rows: list[tuple], scored: bool = True) -> Labels:
    """rows: (name, (x1, y1, x2, y2), (x, y, z, l, w, h, yaw), score)."""
    if not rows:
        return Labels.empty(with_scores=scored)
    return Labels(
        names=np.array([r[0] for r in rows], dtype=object),
        boxes_2d=Boxes2D(np.array([r[1] for r in rows], dtype=np.float64)),
        boxes_3d=Boxes3D(np.array([r[2] for r in rows], dtype=np.float64)),
        truncated=np.zeros(len(rows)),
        occluded=np.zeros(len(rows), dtype=np.int64),
        alpha=np.zeros(len(rows)),
        scores=np.array([r[3] for r in rows], dtype=np.float64) if scored else None,
    )


def car_box(x: float, y: float = 0.0, length: float = 4.0) -> tuple:
    return (x, y, -0.8, length, 1.6, 1.5, 0.0)


NO_3D = (0.0,) * 7


def test_hand_computed_precision_and_recall():
    gt = labels(
        [
            ("Car", (0, 0, 100, 100), car_box(10), None),
            ("Car", (200, 0, 300, 100), car_box(20), None),
            ("Pedestrian", (400, 0, 450, 100), (30, 0, -0.9, 0.8, 0.6, 1.75, 0.0), None),
            ("DontCare", (500, 0, 600, 50), NO_3D, None),
        ],
        scored=False,
    )
    pseudo = labels(
        [
            ("Car", (0, 0, 100, 100), car_box(10), 0.9),  # TP in both modalities
            ("Car", (0, 0, 100, 95), car_box(10.2), 0.8),  # duplicate of the first: FP
            ("Car", (200, 0, 260, 100), car_box(22), 0.7),  # IoU 0.6 (2D), 1/3 (3D): FP
            ("Pedestrian", (400, 0, 450, 100), (30, 0, -0.9, 0.8, 0.6, 1.75, 0.0), 0.6),
            ("Car", (510, 0, 590, 50), car_box(-30), 0.5),  # on the DontCare region: FP
        ]
    )
    result = pseudo_label_quality([pseudo], [gt], ["Car", "Pedestrian", "Cyclist"], IOU_3D, IOU_2D)
    for modality in ("3d", "2d"):
        car = result["Car"][modality]
        assert (car["tp"], car["num_pseudo"], car["num_gt"]) == (1, 4, 2)
        assert car["precision"] == pytest.approx(0.25) and car["recall"] == pytest.approx(0.5)
        pedestrian = result["Pedestrian"][modality]
        assert (pedestrian["precision"], pedestrian["recall"]) == (1.0, 1.0)
        cyclist = result["Cyclist"][modality]
        assert cyclist == {"precision": 0.0, "recall": 0.0, "tp": 0, "num_pseudo": 0,
                           "num_gt": 0, "iou_threshold": 0.5}  # fmt: skip
    assert result["Car"]["3d"]["iou_threshold"] == 0.7


def test_matching_is_greedy_by_score_and_one_to_one():
    gt = labels(
        [
            ("Car", (0, 0, 100, 100), car_box(0), None),
            ("Car", (0, 0, 100, 100), car_box(1.0), None),
        ],
        scored=False,
    )
    # The high-scoring box overlaps the second ground truth best and takes it; the other box
    # only overlaps that one, so it is a false positive (an optimal assignment would find 2).
    pseudo = labels(
        [("Car", (0, 0, 1, 1), car_box(1.0), 0.9), ("Car", (0, 0, 1, 1), car_box(1.3), 0.8)]
    )
    quality = pseudo_label_quality([pseudo], [gt], ["Car"], {"Car": 0.6}, {"Car": 0.7})
    assert quality["Car"]["3d"]["tp"] == 1
    # Without scores the order of the rows decides.
    swapped = labels(
        [("Car", (0, 0, 1, 1), car_box(1.3), 0.0), ("Car", (0, 0, 1, 1), car_box(0.2), 0.0)],
        scored=False,
    )
    quality = pseudo_label_quality([swapped], [gt], ["car"], {"car": 0.6}, {"car": 0.7})
    assert quality["car"]["3d"]["tp"] == 2


def test_rows_without_a_box_in_a_modality_do_not_count_there():
    gt = labels([("Car", (0, 0, 100, 100), car_box(0), None)], scored=False)
    only_2d = labels([("Car", (0, 0, 100, 100), NO_3D, 0.9)])
    quality = pseudo_label_quality([only_2d], [gt], ["Car"], IOU_3D, IOU_2D)
    assert quality["Car"]["2d"]["tp"] == 1 and quality["Car"]["2d"]["num_pseudo"] == 1
    assert quality["Car"]["3d"]["num_pseudo"] == 0 and quality["Car"]["3d"]["num_gt"] == 1


def test_errors():
    with pytest.raises(ValueError, match="2 pseudo-label frames but 1"):
        pseudo_label_quality([labels([]), labels([])], [labels([])], ["Car"], IOU_3D, IOU_2D)
    with pytest.raises(ValueError, match="no 3D IoU threshold for class 'Van'"):
        pseudo_label_quality([labels([])], [labels([])], ["Van"], IOU_3D, IOU_2D)


def brute_force(pseudo, gt, name, modality, threshold):
    """Per frame: sort by score, each takes the best free ground truth at >= threshold."""
    tp = num_pseudo = num_gt = 0
    for p, g in zip(pseudo, gt, strict=True):

        def rows(x):
            keep = []
            for i in range(len(x)):
                if str(x.names[i]).lower() != name.lower():
                    continue
                if modality == "3d" and not np.all(x.boxes_3d.data[i, 3:6] > 0):
                    continue
                keep.append(i)
            return keep

        pi, gi = rows(p), rows(g)
        num_pseudo, num_gt = num_pseudo + len(pi), num_gt + len(gi)
        pi.sort(key=lambda i: -p.scores[i])
        free = set(gi)
        for i in pi:
            best, best_iou = None, -1.0
            for j in sorted(free):
                if modality == "3d":
                    iou = pairwise_iou_3d(p.boxes_3d.data[i : i + 1], g.boxes_3d.data[j : j + 1])
                else:
                    iou = pairwise_iou_2d(p.boxes_2d.xyxy[i : i + 1], g.boxes_2d.xyxy[j : j + 1])
                if iou[0, 0] > best_iou:
                    best, best_iou = j, iou[0, 0]
            if best is not None and best_iou >= threshold:
                free.remove(best)
                tp += 1
    return tp, num_pseudo, num_gt


@pytest.mark.parametrize("seed", range(3))
def test_random_frames_agree_with_brute_force(seed):
    rng = np.random.default_rng(seed)
    names = np.array(["Car", "Pedestrian", "Cyclist", "DontCare"])
    gt, pseudo = [], []
    for _ in range(15):
        n = int(rng.integers(0, 7))
        rows = []
        for _ in range(n):
            centre = rng.uniform([-10, -10, -1], [10, 10, 0])
            box = (*centre, *rng.uniform([3, 1.4, 1.3], [5, 1.9, 1.7]), rng.uniform(-3, 3))
            x1, y1 = rng.uniform(0, 300, 2)
            rows.append((str(rng.choice(names)), (x1, y1, x1 + 60, y1 + 50), box, None))
        gt.append(labels(rows, scored=False))
        guesses = []
        for name, box2d, box3d, _ in rows:
            for _ in range(int(rng.integers(0, 3))):
                noisy3d = np.array(box3d) + rng.normal(0, 0.3, 7) * [1, 1, 0.2, 0.2, 0.1, 0.1, 0.3]
                noisy2d = np.array(box2d) + rng.normal(0, 6, 4)
                label = name if rng.random() < 0.8 else str(rng.choice(names[:3]))
                guesses.append((label, tuple(noisy2d), tuple(noisy3d), float(rng.random())))
        pseudo.append(labels(guesses))
    classes = ["Car", "Pedestrian", "Cyclist"]
    quality = pseudo_label_quality(pseudo, gt, classes, IOU_3D, IOU_2D)
    for name in classes:
        for modality, thresholds in (("3d", IOU_3D), ("2d", IOU_2D)):
            got = quality[name][modality]
            expected = brute_force(pseudo, gt, name, modality, thresholds[name])
            assert (got["tp"], got["num_pseudo"], got["num_gt"]) == expected
    assert any(quality[c][m]["tp"] for c in classes for m in ("3d", "2d"))


def test_pooled_precision_recall_f1_sums_counts_before_dividing():
    """Pooling runs sums true positives, pseudo-labels and objects: a run with few labels
    weighs by its counts, not as a mean of ratios; nothing labeled gives zeros, not an error."""
    rows = [{"tp": 9, "num_pseudo": 10, "num_gt": 30}, {"tp": 0, "num_pseudo": 10, "num_gt": 0}]
    precision, recall, f1 = pooled_precision_recall_f1(rows)
    assert precision == pytest.approx(0.45) and recall == pytest.approx(0.3)
    assert f1 == pytest.approx(2 * 0.45 * 0.3 / 0.75)
    assert pooled_precision_recall_f1([{"tp": 0, "num_pseudo": 0, "num_gt": 0}]) == (0.0, 0.0, 0.0)
