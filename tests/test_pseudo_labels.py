import numpy as np
import pytest

from detmatch.data.kitti import read_calib
from detmatch.geometry import project_boxes_to_image
from detmatch.matching_policy import MatchingPolicy
from detmatch.pseudo_labels import Provenance, confident_detections, match_detections
from detmatch.structures import Detections
from tests.conftest import KITTI_SAMPLE

IMAGE = (1242, 375)
PAPER = MatchingPolicy()  # tau_hung -1.5, outside-view fallback 0.3, no in-view LiDAR-only


@pytest.fixture(scope="module")
def calib():
    return read_calib(KITTI_SAMPLE / "training" / "calib" / "000001.txt")


def detections(boxes, probabilities):
    boxes = np.asarray(boxes, dtype=float).reshape(len(probabilities), -1)
    probabilities = np.asarray(probabilities, dtype=float)
    return Detections(boxes, probabilities.max(1), probabilities.argmax(1), probabilities)


def test_only_objects_both_sensors_agree_on_become_labels(calib):
    car = [15.0, 2.0, -0.9, 3.9, 1.6, 1.5, 0.2]
    pole = [12.0, -4.0, -0.8, 0.5, 0.5, 1.8, 0.0]  # the LiDAR thinks it is a pedestrian
    far_behind = [-20.0, 0.0, -0.9, 3.9, 1.6, 1.5, 0.0]  # outside the camera's view
    det_3d = detections(
        [car, pole, far_behind], [[0.8, 0.1, 0.1], [0.1, 0.6, 0.1], [0.5, 0.1, 0.1]]
    )
    car_2d = project_boxes_to_image(np.array([car]), calib, IMAGE)[0] + [2, -1, -3, 2]
    det_2d = detections([car_2d], [[0.85, 0.05, 0.1]])

    labels = match_detections(det_3d, det_2d, calib, IMAGE, PAPER)
    assert labels.provenance.tolist() == [Provenance.MATCHED, Provenance.LIDAR_ONLY_OUTSIDE_VIEW]
    assert labels.index_3d.tolist() == [0, 2] and labels.index_2d.tolist() == [0, -1]
    np.testing.assert_array_equal(labels.boxes_2d[0], car_2d)
    assert labels.cost[0] < -1.5 and np.isnan(labels.cost[1])
    assert labels.class_3d.tolist() == [0, 0] and labels.class_2d.tolist() == [0, -1]

    no_fallback = match_detections(
        det_3d, det_2d, calib, IMAGE, MatchingPolicy(tau_3d_outside_view=None)
    )
    assert no_fallback.provenance.tolist() == [Provenance.MATCHED]
    strict = match_detections(det_3d, det_2d, calib, IMAGE, MatchingPolicy(tau_hung=-10.0))
    assert strict.matched.sum() == 0


def test_confident_unmatched_3d_detections_in_view_can_become_lidar_only_labels(calib):
    """tau_3d_unmatched keeps in-view 3D boxes the camera did not confirm when their score
    exceeds it (after the matched rows and the outside-view ones); None keeps none."""
    car = [15.0, 2.0, -0.9, 3.9, 1.6, 1.5, 0.2]
    person = [12.0, -4.0, -0.8, 0.6, 0.6, 1.8, 0.0]  # in view; the camera misses it
    faint = [20.0, 5.0, -0.8, 0.6, 0.6, 1.8, 0.0]
    far_behind = [-20.0, 0.0, -0.9, 3.9, 1.6, 1.5, 0.0]
    det_3d = detections(
        [car, person, faint, far_behind],
        [[0.8, 0.1, 0.1], [0.1, 0.7, 0.1], [0.1, 0.4, 0.1], [0.5, 0.1, 0.1]],
    )
    det_2d = detections([project_boxes_to_image(np.array([car]), calib, IMAGE)[0]],
                        [[0.85, 0.05, 0.1]])  # fmt: skip

    labels = match_detections(det_3d, det_2d, calib, IMAGE, MatchingPolicy(tau_3d_unmatched=0.6))
    assert labels.provenance.tolist() == [
        Provenance.MATCHED, Provenance.LIDAR_ONLY_OUTSIDE_VIEW, Provenance.LIDAR_ONLY_CONFIDENT,
    ]  # fmt: skip
    assert labels.index_3d.tolist() == [0, 3, 1] and labels.index_2d.tolist() == [0, -1, -1]
    assert labels.class_3d.tolist() == [0, 0, 1] and labels.class_2d.tolist() == [0, -1, -1]
    assert np.isnan(labels.boxes_2d[2]).all() and np.isnan(labels.cost[2])
    # The faint one (0.4) stays out at 0.6 and comes in at 0.3; None is the paper's rule.
    assert match_detections(
        det_3d, det_2d, calib, IMAGE, MatchingPolicy(tau_3d_unmatched=0.3)
    ).index_3d.tolist() == [0, 3, 1, 2]
    assert match_detections(det_3d, det_2d, calib, IMAGE, PAPER).index_3d.tolist() == [0, 3]
    # A box the matching paired is never counted twice, however confident.
    assert match_detections(
        det_3d, det_2d, calib, IMAGE, MatchingPolicy(tau_3d_unmatched=0.0)
    ).index_3d.tolist() == [0, 3, 1, 2]


def test_no_detections(calib):
    empty = Detections(np.zeros((0, 7)), np.zeros(0), np.zeros(0, dtype=int), np.zeros((0, 3)))
    empty_2d = Detections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=int), np.zeros((0, 3)))
    labels = match_detections(empty, empty_2d, calib, IMAGE, PAPER)
    assert len(labels) == 0 and labels.boxes_3d.shape == (0, 7) and labels.boxes_2d.shape == (0, 4)


def test_confidence_thresholding():
    det = detections(np.zeros((3, 4)), [[0.9, 0.0, 0.0], [0.2, 0.5, 0.0], [0.1, 0.0, 0.75]])
    assert confident_detections(det, 0.7).classes.tolist() == [0, 2]


def test_label_classes_are_the_argmax_of_the_probabilities(calib):
    """A peak decoded in one class channel whose probability vector favours another class is
    labeled with the argmax, the class the matching cost compared (docs/design.md step 3)."""
    car = [15.0, 2.0, -0.9, 3.9, 1.6, 1.5, 0.2]
    probabilities = np.array([[0.35, 0.05, 0.9]])
    det_3d = Detections(np.array([car]), np.array([0.35]), np.array([0]), probabilities)
    car_2d = project_boxes_to_image(np.array([car]), calib, IMAGE)
    det_2d = Detections(car_2d, np.array([0.6]), np.array([1]), np.array([[0.1, 0.6, 0.95]]))
    labels = match_detections(det_3d, det_2d, calib, IMAGE, PAPER)
    assert labels.class_3d.tolist() == [2] and labels.class_2d.tolist() == [2]


def test_detmatch_keeps_lidar_only_labels_out_of_the_2d_background(calib):
    """The in-view LiDAR-only labels' image projections are the 2D ignore regions (the 2D
    student learns no background where only the LiDAR saw something); the 2D labels stay the
    matched pairs, outside-view fallbacks (not in the image) add none, and every other
    unmatched detection is background."""
    from detmatch.training.rules import DetMatchRule

    car = [15.0, 2.0, -0.9, 3.9, 1.6, 1.5, 0.2]
    person = [12.0, -4.0, -0.8, 0.6, 0.6, 1.8, 0.0]  # in view; the camera misses it
    far_behind = [-20.0, 0.0, -0.9, 3.9, 1.6, 1.5, 0.0]
    det_3d = detections([car, person, far_behind],
                        [[0.8, 0.1, 0.1], [0.1, 0.7, 0.1], [0.5, 0.1, 0.1]])  # fmt: skip
    car_2d = project_boxes_to_image(np.array([car]), calib, IMAGE)[0]
    rider_2d = [100.0, 150.0, 130.0, 230.0]  # unmatched 2D: background
    det_2d = detections([car_2d, rider_2d], [[0.85, 0.05, 0.1], [0.1, 0.1, 0.5]])

    rule = DetMatchRule(MatchingPolicy(tau_3d_unmatched=0.6), 4.0, False)
    protected = rule.frame_labels(det_2d, det_3d, calib, IMAGE)
    person_2d = project_boxes_to_image(np.array([person]), calib, IMAGE)
    assert (person_2d[:, 2:] > person_2d[:, :2]).all()  # it lands in the image
    np.testing.assert_allclose(protected.ignore_2d.boxes, person_2d)
    assert protected.ignore_2d.classes.tolist() == [1]
    np.testing.assert_allclose(protected.ignore_2d.probabilities, [[0.1, 0.7, 0.1]])
    np.testing.assert_array_equal(protected.labels_2d.boxes, [car_2d])
    np.testing.assert_array_equal(protected.labels_3d.boxes, [car, far_behind, person])
    # The paper's policy makes no in-view LiDAR-only labels, so no ignore regions.
    paper = DetMatchRule(PAPER, 4.0, False).frame_labels(det_2d, det_3d, calib, IMAGE)
    assert len(paper.ignore_2d) == 0
    np.testing.assert_array_equal(paper.labels_3d.boxes, [car, far_behind])
