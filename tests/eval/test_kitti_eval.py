import numpy as np
import pytest

from detmatch.eval.kitti import (
    METRICS,
    canonical_classes,
    evaluate,
    evaluate_curves,
    format_table,
)
from detmatch.eval.kitti_overlaps import concatenate_objects, frame_overlaps
from tests.eval.helpers import (
    PLACEHOLDER_3D,
    frame,
    noisy_detections,
    random_scene,
    row,
    with_scores,
)
from tests.eval.kitti_reference import reference_evaluate

BBOX, BEV, D3 = (METRICS.index(m) for m in ("bbox", "bev", "3d"))
EASY, MODERATE, HARD = 0, 1, 2


def counts(curves, metric: int, difficulty: int, c: int = 0) -> list[tuple[int, int, int]]:
    """(TP, FP, FN) at each chosen threshold."""
    n = curves.num_thresholds[c, metric, difficulty]
    return [
        tuple(int(v[c, metric, difficulty, t]) for v in (curves.tp, curves.fp, curves.fn))
        for t in range(n)
    ]


def car(x: float, score: float | None = None, **kwargs) -> dict:
    """A 100 x 100 px Car at x (easy for ground truth)."""
    return row(kwargs.pop("name", "Car"), (x, 100.0, x + 100.0, 200.0), score=score, **kwargs)


def assert_same_results(result: dict, expected: dict) -> None:
    """Same classes, keys and order; AP equal up to summation order."""
    assert list(result) == list(expected)
    for name, per_class in expected.items():
        assert list(result[name]) == list(per_class)
        for recall, table in per_class.items():
            assert list(result[name][recall]) == list(table)
            for metric, values in table.items():
                np.testing.assert_allclose(
                    result[name][recall][metric], values, rtol=0, atol=1e-9,
                    err_msg=f"{name} {recall} {metric}",
                )  # fmt: skip


# ------------------------------------------------------------------ hand-computed small cases


def test_hand_computed_precision_recall_curve():
    gt = [frame([car(0), car(200), car(400), car(600)])]
    dt = [
        frame(
            [
                car(0, 0.9),  # TP on gt 0
                car(900, 0.8),  # FP
                car(200, 0.7),  # TP on gt 1
                row("Car", (400.0, 100.0, 460.0, 200.0), score=0.6),  # IoU 0.6 < 0.7: FP
            ]
        )
    ]
    curves = evaluate_curves(gt, dt, ["Car"])
    np.testing.assert_array_equal(curves.thresholds[0, BBOX, EASY, :2], [0.9, 0.7])
    assert counts(curves, BBOX, EASY) == [(1, 0, 3), (2, 1, 2)]
    np.testing.assert_allclose(curves.recall()[0, BBOX, EASY, :2], [0.25, 0.5])
    expected = np.zeros(41)
    expected[:2] = [1.0, 2 / 3]
    np.testing.assert_allclose(curves.precision()[0, BBOX, EASY], expected)
    result = evaluate(gt, dt, ["Car"])
    assert result["Car"]["R40"]["bbox"][EASY] == pytest.approx(100 * (2 / 3) / 40)
    assert result["Car"]["R11"]["bbox"][EASY] == pytest.approx(100 / 11)


def test_precision_is_made_monotone_over_higher_recall():
    gt = [frame([car(0), car(200), car(400)])]
    # Ranked FP, TP, TP: raw precision 1/2 then 2/3 at the TP scores 0.8 and 0.7.
    dt = [frame([car(900, 0.9), car(0, 0.8), car(200, 0.7)])]
    curves = evaluate_curves(gt, dt, ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 1, 2), (2, 1, 1)]
    np.testing.assert_allclose(curves.precision()[0, BBOX, EASY, :3], [2 / 3, 2 / 3, 0.0])


def test_neighbour_class_is_neither_true_nor_false_positive():
    dets = [car(0, 0.9), car(300, 0.5)]
    van = evaluate_curves([frame([car(0, name="Van"), car(300)])], [frame(dets)], ["Car"])
    assert counts(van, BBOX, EASY) == [(1, 0, 0)]
    assert van.num_valid_gt[0, EASY] == 1
    truck = evaluate_curves([frame([car(0, name="Truck"), car(300)])], [frame(dets)], ["Car"])
    assert counts(truck, BBOX, EASY) == [(1, 1, 0)]
    sitting = [frame([car(0, name="Person_sitting"), car(300, name="Pedestrian")])]
    walkers = [frame([car(0, 0.9, name="Pedestrian"), car(300, 0.5, name="Pedestrian")])]
    assert counts(evaluate_curves(sitting, walkers, ["Pedestrian"]), BBOX, EASY) == [(1, 0, 0)]
    # Van is its own class with no neighbour: a Car ground truth does not shield a Van detection.
    vans = evaluate_curves(
        [frame([car(0), car(300, name="Van")])],
        [frame([car(0, 0.9, name="Van"), car(300, 0.5, name="Van")])],
        ["Van"],
    )
    assert counts(vans, BBOX, EASY) == [(1, 1, 0)]


def test_detections_in_dontcare_regions_are_ignored_for_the_2d_metric_only():
    dontcare = row("DontCare", (500.0, 100.0, 600.0, 200.0))
    inside = row("Car", (510.0, 110.0, 590.0, 190.0), score=0.9)  # all of it in the region
    gt = [frame([car(0), dontcare])]
    curves = evaluate_curves(gt, [frame([inside, car(0, 0.5)])], ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 0, 0)]
    assert counts(curves, BEV, EASY) == [(1, 1, 0)]
    assert counts(curves, D3, EASY) == [(1, 1, 0)]
    # 60 % of the detection inside: over Pedestrian's 0.5, under Car's 0.7 (area of the detection).
    for name, fp in (("Car", 1), ("Pedestrian", 0)):
        gt = [frame([car(0, name=name), dontcare])]
        partial = row(name, (540.0, 100.0, 640.0, 200.0), score=0.9)
        dt = [frame([car(0, 0.5, name=name), partial])]
        curves = evaluate_curves(gt, dt, [name])
        assert counts(curves, BBOX, EASY) == [(1, fp, 0)]


def test_detections_under_the_minimum_height_are_ignored():
    short = row("Car", (600.0, 100.0, 700.0, 130.0), score=0.9)  # 30 px, overlaps nothing
    curves = evaluate_curves([frame([car(0)])], [frame([short, car(0, 0.5)])], ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 0, 0)]  # < 40 px: ignored
    assert counts(curves, BBOX, MODERATE) == [(1, 1, 0)]  # >= 25 px: a false positive
    # A too-small detection on a valid ground truth absorbs it: no TP, no FN (both codes).
    gt = [frame([row("Car", (0.0, 100.0, 100.0, 141.0)), car(300)])]
    dt = [frame([row("Car", (0.0, 100.0, 100.0, 136.0), score=0.9), car(300, 0.5)])]
    curves = evaluate_curves(gt, dt, ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 0, 0)]
    assert counts(curves, BBOX, MODERATE) == [(1, 0, 1), (2, 0, 0)]


def test_too_small_detection_of_another_class_absorbs_ground_truth_as_officially():
    # The devkit marks every detection under the minimum height as ignored before looking at
    # its class, so a small Pedestrian detection on a Car hides the Car from the easy count.
    gt = [frame([row("Car", (0.0, 100.0, 100.0, 141.0)), car(300)])]
    dt = [frame([row("Pedestrian", (0.0, 100.0, 100.0, 136.0), score=0.9), car(300, 0.5)])]
    curves = evaluate_curves(gt, dt, ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 0, 0)]
    assert counts(curves, BBOX, MODERATE) == [(1, 0, 1)]  # 36 px counts at moderate: a miss


def test_ground_truth_difficulty_rules():
    gt = [
        frame(
            [
                car(0, occ=1),  # moderate
                car(200, trunc=0.2),  # moderate
                row("Car", (400.0, 100.0, 500.0, 130.0)),  # 30 px: moderate
                row("Car", (600.0, 100.0, 700.0, 140.0)),  # exactly 40 px: easy (devkit's <)
                row("Car", (800.0, 100.0, 900.0, 139.99)),  # just under 40 px: moderate
                car(1000, occ=2, trunc=0.45),  # hard
            ]
        )
    ]
    assert evaluate_curves(gt, [frame([])], ["Car"]).num_valid_gt.tolist() == [[1, 5, 6]]
    dt = [frame([row("Car", tuple(b), score=0.5) for b in gt[0].bbox])]
    curves = evaluate_curves(gt, dt, ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 0, 0)]  # the rest are ignored, not FP
    assert counts(curves, BBOX, HARD) == [(6, 0, 0)] * 6  # six tied TP scores


def test_overlap_threshold_is_strict():
    gt = [frame([car(0), car(300)])]
    exact = row("Car", (0.0, 100.0, 70.0, 200.0), score=0.9)  # IoU exactly 0.7
    curves = evaluate_curves(gt, [frame([exact, car(300, 0.5)])], ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 1, 1)]
    above = row("Car", (0.0, 100.0, 70.01, 200.0), score=0.9)
    curves = evaluate_curves(gt, [frame([above, car(300, 0.5)])], ["Car"])
    assert counts(curves, BBOX, EASY) == [(1, 0, 1), (2, 0, 0)]


def test_class_names_match_case_insensitively():
    gt = [frame([car(0, name="car")])]
    dt = [frame([car(0, 0.9, name="CAR")])]
    curves = evaluate_curves(gt, dt, ["cAr"])
    assert curves.classes == ("Car",)
    assert counts(curves, BBOX, EASY) == [(1, 0, 0)]
    assert canonical_classes(["PEDESTRIAN", "person_sitting", "Pedestrian"]) == (
        "Pedestrian",
        "Person_sitting",
    )


def test_unknown_class_is_an_error():
    with pytest.raises(ValueError, match="unknown KITTI class 'Bus'"):
        evaluate([frame([])], [frame([])], ["Car", "Bus"])
    with pytest.raises(ValueError, match="2 ground-truth frames but 1"):
        evaluate([frame([]), frame([])], [frame([])], ["Car"])


def test_orientation_similarity():
    num = 50
    gt = [frame([car(0, alpha=0.3)]) for _ in range(num)]
    dt = [frame([car(0, 0.5 + i / 100, alpha=0.3 + np.pi / 2)]) for i in range(num)]
    result = evaluate(gt, dt, ["Car"])["Car"]
    assert result["R40"]["bbox"] == [100.0] * 3
    np.testing.assert_allclose(result["R40"]["aos"], [50.0] * 3)
    # A single placeholder alpha turns AOS off for the whole result set (devkit rule).
    dt[3] = frame([car(0, 0.5, alpha=-10.0)])
    assert "aos" not in evaluate(gt, dt, ["Car"])["Car"]["R40"]


def test_class_without_valid_ground_truth_scores_zero():
    gt = [frame([car(0, occ=3), row("Pedestrian", (0.0, 100.0, 50.0, 200.0))])]
    dt = [frame([car(0, 0.9)])]
    result = evaluate(gt, dt, ["Car", "Cyclist"])
    for name in ("Car", "Cyclist"):
        for table in result[name].values():
            assert list(table) == ["bbox", "bev", "3d", "aos"]
            assert all(v == [0.0, 0.0, 0.0] for v in table.values())


def test_two_d_only_results_give_only_bbox_numbers():
    rng = np.random.default_rng(3)
    gt = random_scene(rng, 30)
    dt = noisy_detections(rng, gt)
    with_3d = evaluate(gt, dt, ["Car", "Pedestrian"])
    flat = []
    for objects in dt:
        rows = [
            row(str(objects.names[i]), tuple(objects.bbox[i]), score=objects.score[i], alpha=-10.0)
            for i in range(len(objects))
        ]
        flat.append(frame([{**r, **PLACEHOLDER_3D} for r in rows], scored=True))
    only_2d = evaluate(gt, flat, ["Car", "Pedestrian"])
    for name in ("Car", "Pedestrian"):
        for recall in ("R40", "R11"):
            assert list(only_2d[name][recall]) == ["bbox"]
            assert only_2d[name][recall]["bbox"] == with_3d[name][recall]["bbox"]
    assert_same_results(only_2d, reference_evaluate(gt, flat, ["Car", "Pedestrian"]))
    assert "2D-only" in format_table(only_2d)


# --------------------------------------------------------------- perfect and sample-count runs


def test_perfect_predictions_on_many_objects_give_100_everywhere():
    rng = np.random.default_rng(0)
    gt = random_scene(
        rng, 80, max_objects=8, classes=("Car", "Pedestrian", "Cyclist"), easy_only=True
    )
    names = np.concatenate([g.names for g in gt])
    assert min(np.count_nonzero(names == c) for c in ("Car", "Pedestrian", "Cyclist")) > 60
    dt = [with_scores(g, rng.uniform(0.1, 1.0, len(g))) for g in gt]
    result = evaluate(gt, dt, ["Car", "Pedestrian", "Cyclist"])
    for per_class in result.values():
        for table in per_class.values():
            assert list(table) == ["bbox", "bev", "3d", "aos"]
            for values in table.values():
                np.testing.assert_allclose(values, [100.0] * 3, rtol=0, atol=1e-9)


@pytest.mark.parametrize("num", [1, 2, 3, 10, 39, 40, 41, 42, 60])
def test_sample_count_effect_matches_the_official_thresholds(num):
    gt = [frame([car(0)]) for _ in range(num)]
    dt = [frame([car(0, 0.2 + 0.7 * i / num)]) for i in range(num)]
    result = evaluate(gt, dt, ["Car"])["Car"]
    points = min(num, 41)  # thresholds the official getThresholds can pick
    assert result["R40"]["bbox"][EASY] == pytest.approx(100 * (points - 1) / 40)
    assert result["R11"]["bbox"][EASY] == pytest.approx(100 * len(range(0, points, 4)) / 11)
    assert_same_results({"Car": result}, reference_evaluate(gt, dt, ["Car"]))


def test_identical_rotated_boxes_overlap_with_iou_one():
    rng = np.random.default_rng(1)
    gt = random_scene(rng, 5, easy_only=True)
    dt = [with_scores(g, np.ones(len(g))) for g in gt]
    overlaps, offsets = frame_overlaps(concatenate_objects(gt), concatenate_objects(dt))
    for f, g in enumerate(gt):
        n = len(g)
        for metric in ("bbox", "bev", "3d"):
            block = overlaps[metric][offsets[f] : offsets[f + 1]].reshape(n, n)
            np.testing.assert_allclose(np.diag(block), 1.0, rtol=0, atol=1e-12)


# ------------------------------------------------------------------- brute-force comparisons


@pytest.mark.parametrize("seed", range(6))
def test_random_scenes_agree_with_the_brute_force_reference(seed):
    rng = np.random.default_rng(seed)
    gt = random_scene(rng, 30 + 6 * seed, max_objects=10)
    dt = noisy_detections(rng, gt, noise=0.5 + 0.2 * seed)
    classes = ["Car", "Pedestrian", "Cyclist"] if seed % 3 else ["Car", "Van", "Pedestrian"]
    result = evaluate(gt, dt, classes)
    assert_same_results(result, reference_evaluate(gt, dt, classes))
    # The sets are rich enough to exercise the rules: something matched, something not.
    assert any(0.0 < v < 100.0 for c in result.values() for v in c["R11"]["bbox"])
