"""The frame picture a person reads: no text over another text, predictions told apart from
ground truth in both panels."""

import numpy as np
import pytest

from detmatch.data.kitti import KittiDataset, parse_objects
from detmatch.data.visualize import (
    CLASS_COLOURS,
    TextLayout,
    draw_bev_panel,
    render_frame_picture,
)


def _predictions_from_labels(kitti_sample, frame_id: str, jitter_px: float):
    """The frame's own label rows as predictions with scores, 2D boxes moved by jitter_px."""
    rows = (kitti_sample / "training" / "label_2" / f"{frame_id}.txt").read_text().splitlines()
    moved = []
    for k, row in enumerate(rows):
        fields = row.split()
        for i in (4, 5, 6, 7):
            fields[i] = f"{float(fields[i]) + jitter_px:.2f}"
        moved.append(" ".join(fields) + f" {0.5 + 0.05 * k:.2f}")
    return parse_objects("\n".join(moved) + "\n", f"{frame_id}.txt")


def _overlapping(boxes):
    return [
        (a, b)
        for i, a in enumerate(boxes)
        for b in boxes[i + 1 :]
        if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
    ]


@pytest.mark.parametrize("frame_id", ["000000", "000001", "000002"])
def test_no_text_overlaps_another_and_all_stay_in_the_picture(kitti_sample, frame_id):
    # 000001 has four DontCare boxes side by side and a cyclist beside a car: the labels that
    # used to print over each other ("DDDontCare...").
    frame = KittiDataset(kitti_sample).load_frame(frame_id)
    predictions = _predictions_from_labels(kitti_sample, frame_id, jitter_px=3.0)
    layout = TextLayout((0, 0))
    picture = render_frame_picture(frame, predictions, layout=layout)
    assert len(layout.boxes) >= 9  # caption, legend entries, distance marks, box labels
    assert _overlapping(layout.boxes) == []
    width, height = picture.size
    assert all(
        0 <= x1 and 0 <= y1 and x2 <= width and y2 <= height for x1, y1, x2, y2 in layout.boxes
    )


def test_the_caption_and_the_legend_do_not_share_a_row(kitti_sample):
    frame = KittiDataset(kitti_sample).load_frame("000001")
    layout = TextLayout((0, 0))
    render_frame_picture(frame, _predictions_from_labels(kitti_sample, "000001", 0.0), layout)
    strip = [b for b in layout.boxes if frame.image_size[1] <= b[1] < frame.image_size[1] + 60]
    caption = min(strip, key=lambda b: (b[1], b[0]))
    below = [b for b in strip if b is not caption]
    assert below and all(b[1] >= caption[3] for b in below)


def test_predictions_look_different_from_ground_truth_in_the_birds_eye_view(kitti_sample):
    # The same boxes drawn as ground truth and as predictions: ground truth is filled and
    # solid, a prediction is a dashed outline, even for a pedestrian a few pixels wide.
    frame = KittiDataset(kitti_sample).load_frame("000000")  # one pedestrian
    objects = KittiDataset(kitti_sample).read_objects("000000")
    from detmatch.data.kitti import objects_to_labels

    as_labels = objects_to_labels(objects, frame.calib)
    empty = frame.__class__(**{**frame.__dict__, "labels": None})
    size = 600
    ground_truth = np.asarray(draw_bev_panel(frame, None, size)).astype(int)
    prediction = np.asarray(draw_bev_panel(empty, as_labels, size)).astype(int)
    colour = np.array(CLASS_COLOURS["Pedestrian"])
    in_colour = lambda pixels: (np.abs(pixels - colour).sum(axis=2) == 0).sum()  # noqa: E731
    tinted = lambda pixels: (np.abs(pixels - colour).sum(axis=2) < 200).sum()  # noqa: E731
    assert in_colour(prediction) < 0.8 * in_colour(ground_truth)  # gaps in the dashed outline
    assert tinted(ground_truth) > tinted(prediction)  # the ground truth's fill
