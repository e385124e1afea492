"""`detmatch review export`: CVAT 3D sets that datumaro's own importers read back (boxes within
1e-4 m / rad of the stored labels, the related image, a calibration that projects as P2 . R0 .
Tr does), Label Studio tasks whose pre-annotations are the stored 2D boxes, and the frame
selections (every frame, a seeded audit sample, the lowest 3D scores, the most cross-modal
disagreement), and the disagreement signals one by one."""

from __future__ import annotations

import copy
import json
import os

import numpy as np
import pytest

if os.environ.get("DETMATCH_REQUIRE_REVIEW"):  # .ci/run installs the review extra
    import datumaro as dm
else:
    dm = pytest.importorskip("datumaro", reason="the review extra: pip install -e '.[review]'")

from commands.main import main  # noqa: E402
from detmatch.data.kitti import KittiDataset  # noqa: E402
from serving.review import (  # noqa: E402
    DATUMARO_FORMAT,
    camera_matrices,
    disagreement,
    drawable,
    export_review,
    select_frames,
)
from serving.reviews import import_review, read_human_labels  # noqa: E402
from serving.store import list_frames  # noqa: E402
from tests.conftest import KITTI_SAMPLE  # noqa: E402


def _stored_boxes(store) -> dict[str, list[tuple[str, list[float]]]]:
    frames = select_frames(store)
    return {
        f"{s.record.namespace}__{s.record.frame_id}": [
            (label["class_3d"], label["box_3d"]) for label in s.labels["labels"]
        ]
        for s in frames
    }


def test_a_cvat_3d_export_imports_with_datumaro_as_the_stored_labels(store, tmp_path):
    from datumaro.components import annotation

    out = tmp_path / "cvat"
    summary = export_review(store, out, "cvat-3d", select_frames(store))
    stored = _stored_boxes(store)
    assert summary.frames == 4 and summary.labels == sum(map(len, stored.values())) > 0
    annotation.COORDINATE_ROUNDING_DIGITS = 6
    dataset = dm.Dataset.import_from(str(out), "sly_pointcloud")
    classes = dataset.categories()[dm.AnnotationType.label]
    assert {item.id for item in dataset} == set(stored)
    labels_spec = json.loads((out / "cvat_labels.json").read_text())
    assert all(lb["type"] == "cuboid" for lb in labels_spec)
    for item in dataset:
        got = sorted((classes[c.label].name, [*c.position, *c.scale, c.rotation[2]],
                      c.attributes) for c in item.annotations)  # fmt: skip
        want = sorted(stored[item.id])
        assert len(got) == len(want)
        for (name, box, attributes), (name_want, box_want) in zip(got, want, strict=True):
            assert name == name_want
            np.testing.assert_allclose(box, box_want, atol=1e-4)
            assert attributes["provenance"] in ("matched", "lidar_only_confident",
                                                "lidar_only_outside_view")  # fmt: skip
            assert attributes["model_version"] == "000001"
            # the task's label specification declares every class and attribute it carries
            (spec,) = [lb for lb in labels_spec if lb["name"] == name]
            assert {a["name"] for a in spec["attributes"]} == set(attributes)
        (image,) = item.media.extra_images
        assert image.data.shape[2] == 3
    # the related image's calibration: K . E projects LiDAR points as P2 . R0 . Tr does
    calib = KittiDataset(KITTI_SAMPLE).load_frame("000001").calib
    (meta_file,) = (out / "ds0" / "related_images" / "default__000001_pcd").glob("*.json")
    meta = json.loads(meta_file.read_text())["meta"]["sensorsData"]
    intrinsic = np.array(meta["intrinsicMatrix"]).reshape(3, 3)
    extrinsic = np.array(meta["extrinsicMatrix"]).reshape(3, 4)
    points = np.array([[10.0, 1.0, -1.0, 1.0], [30.0, -4.0, 0.5, 1.0]])
    projected = (intrinsic @ extrinsic @ points.T).T
    projected = projected[:, :2] / projected[:, 2:]
    rectify, velo = np.eye(4), np.eye(4)
    rectify[:3, :3], velo[:3, :] = calib.R0_rect, calib.Tr_velo_to_cam
    reference = (calib.P2 @ rectify @ velo @ points.T).T
    np.testing.assert_allclose(projected, reference[:, :2] / reference[:, 2:], atol=1e-3)
    assert not np.allclose(camera_matrices(calib)[1], 0)


@pytest.mark.parametrize("format", ["kitti-raw", "datumaro-3d"])
def test_kitti_raw_and_datumaro_3d_exports_import_with_datumaro(store, tmp_path, format):
    from datumaro.components import annotation

    out = tmp_path / "raw"
    export_review(store, out, format, select_frames(store, namespace="default"))
    annotation.COORDINATE_ROUNDING_DIGITS = 6
    dataset = dm.Dataset.import_from(str(out), DATUMARO_FORMAT[format])
    stored = _stored_boxes(store)
    assert {item.id for item in dataset} == {k for k in stored if k.startswith("default__")}
    for item in dataset:
        got = sorted([*c.position, *c.scale, c.rotation[2]] for c in item.annotations)
        want = sorted(box for _, box in stored[item.id])
        np.testing.assert_allclose(got, want, atol=1e-4)
        if format == "datumaro-3d":  # Datumaro 3D keeps the camera image
            (image,) = item.media.extra_images
            assert image.data.shape[2] == 3
    # an accepted review comes back as human 3D labels, the boxes the store holds
    summary = import_review(store, out, format)
    assert len(summary.created) == 3
    human = read_human_labels(store)
    for key, record in human.items():
        assert record["source"] == format
        np.testing.assert_allclose(sorted(lb["box_3d"] for lb in record["labels"]),
                                   sorted(box for _, box in stored["__".join(key)]),
                                   atol=1e-4)  # fmt: skip


def test_label_studio_tasks_carry_the_stored_2d_boxes_as_predictions(store, tmp_path):
    out = tmp_path / "ls"
    export_review(store, out, "label-studio", select_frames(store))
    tasks = json.loads((out / "tasks.json").read_text())
    assert len(tasks) == 4 and "RectangleLabels" in (out / "label_config.xml").read_text()
    by_frame = {s.record.namespace + "__" + s.record.frame_id: s for s in select_frames(store)}
    for task in tasks:
        selected = by_frame[task["data"]["frame"]]
        assert task["data"]["image"] == f"/data/local-files/?d=images/{task['data']['frame']}.png"
        assert (out / "images" / f"{task['data']['frame']}.png").is_file()
        (prediction,) = task["predictions"]
        assert prediction["model_version"] == "000001"
        boxes = [lb for lb in selected.labels["labels"]
                 if lb["box_2d"] is not None and drawable(lb["box_2d"])]  # fmt: skip
        assert len(prediction["result"]) == len(boxes)
        for result, label in zip(prediction["result"], boxes, strict=True):
            value = result["value"]
            width, height = result["original_width"], result["original_height"]
            x1, y1 = value["x"] * width / 100, value["y"] * height / 100
            x2, y2 = x1 + value["width"] * width / 100, y1 + value["height"] * height / 100
            np.testing.assert_allclose([x1, y1, x2, y2], label["box_2d"], atol=1e-6)
            assert value["rectanglelabels"] == [label["class_2d"]]


def test_an_empty_2d_box_is_left_out_of_the_label_studio_tasks(store, tmp_path):
    # A degenerate detection (zero width, as a tiny model can give) cannot be drawn, and the
    # import would refuse it when the reviewer's export brings it back: it is left out.
    selections = copy.deepcopy(select_frames(store))
    labels = next(s for s in selections if s.labels["labels"]).labels["labels"]
    x1, y1, _, y2 = labels[0]["box_2d"] or (10.0, 20.0, 0.0, 40.0)
    labels[0]["box_2d"] = [x1, y1, x1, y2]
    assert not drawable(labels[0]["box_2d"]) and drawable([x1, y1, x1 + 0.5, y2])
    out = tmp_path / "ls"
    export_review(store, out, "label-studio", selections)
    tasks = json.loads((out / "tasks.json").read_text())
    results = [r for task in tasks for r in task["predictions"][0]["result"]]
    want = sum(lb["box_2d"] is not None and drawable(lb["box_2d"])
               for s in selections for lb in s.labels["labels"])  # fmt: skip
    assert len(results) == want
    assert all(r["value"]["width"] > 0 and r["value"]["height"] > 0 for r in results)


def test_selections_pick_an_audit_sample_and_the_least_sure_frames(store, tmp_path, capsys):
    every = select_frames(store)
    assert len(every) == 4
    sample = select_frames(store, "random", budget=2, seed=3)
    assert [s.record.key for s in sample] == [s.record.key for s in select_frames(
        store, "random", budget=2, seed=3)]  # fmt: skip
    assert len(sample) == 2 and "random audit sample (seed 3)" in sample[0].reason
    unsure = select_frames(store, "least-confident", budget=4)
    means = [np.mean([lb["score_3d"] for lb in s.labels["labels"]] or [1.0]) for s in unsure]
    assert means == sorted(means)
    assert unsure[0].reason.startswith(f"mean 3D score {means[0]:.3f}")
    doubt = select_frames(store, "disagreement", budget=4)
    scores = [disagreement(s.labels)[0] for s in doubt]
    assert scores == sorted(scores, reverse=True) and scores[0] > 0
    assert doubt[0].reason == disagreement(doubt[0].labels)[1]
    with pytest.raises(ValueError, match="needs --budget"):
        select_frames(store, "random")
    with pytest.raises(ValueError, match="no stored frame matches"):
        select_frames(store, version="000009")
    assert len(select_frames(store, namespace="site-b")) == 1

    out = tmp_path / "cli"
    assert main(["review", "export", "--store", str(store), "--out", str(out), "--format",
                 "cvat-3d", "--select", "disagreement", "--budget", "2"]) == 0  # fmt: skip
    manifest = json.loads((out / "review.json").read_text())
    assert [f["id"] for f in manifest["frames"]] == [
        f"{s.record.namespace}__{s.record.frame_id}" for s in doubt[:2]
    ]
    assert "exported 2 frames" in capsys.readouterr().out
    assert len(list_frames(store)) == 4  # the store is only read


def test_each_disagreement_signal_counts():
    def label(provenance, class_3d="Car", class_2d="Car", cost=0.1):
        return {"provenance": provenance, "class_3d": class_3d, "class_2d": class_2d,
                "cost": cost, "score_3d": 0.9}  # fmt: skip

    calm = {"thresholds": {"tau_hung": 1.0}, "labels": [label("matched")], "unmatched_2d": []}
    assert disagreement(calm) == (0.0, "no disagreement")
    loud = {
        "thresholds": {"tau_hung": 1.0},
        "labels": [label("matched", class_2d="Pedestrian"), label("matched", cost=0.8),
                   label("lidar_only_confident", class_2d=None, cost=None),
                   label("lidar_only_outside_view", class_2d=None, cost=None)],
        "unmatched_2d": [{"class_2d": "Cyclist", "box_2d": [0, 0, 9, 9], "score_2d": 0.7}] * 2,
    }  # fmt: skip
    assert disagreement(loud) == (
        4.002,
        "1 unconfirmed LiDAR-only labels in view, 1 LiDAR-only labels outside the camera's "
        "view, 1 class disagreements, 1 weak matches, 2 camera-only detections",
    )
    # camera-only detections break ties between frames with as many unconfirmed labels
    seen = {**calm, "unmatched_2d": loud["unmatched_2d"][:1]}
    assert disagreement(seen)[0] > disagreement(calm)[0] and disagreement(seen)[0] < 1
