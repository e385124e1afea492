import json

import numpy as np

from detmatch.cli import main
from detmatch.data.kitti import KittiDataset, read_image_set, read_objects
from detmatch.inference import detections_2d_to_objects, detections_3d_to_objects
from detmatch.structures import Detections
from serving.labeler import Labeler
from serving.serialize import labels_to_objects_2d, labels_to_objects_3d


def test_detmatch_label_writes_kitti_results_that_detmatch_eval_scores(
    exported_repository, synth_root, tmp_path, capsys
):
    out = tmp_path / "labels"
    assert main(["label", "--repository", str(exported_repository), "--data", str(synth_root),
                 "--split", "val", "--out", str(out), "--tau-hung", "50"]) == 0  # fmt: skip
    assert "with model version 000001" in capsys.readouterr().out
    ids = read_image_set(synth_root / "ImageSets" / "val.txt")
    rows = 0
    for frame_id in ids:
        objects_3d = read_objects(out / "3d" / f"{frame_id}.txt")
        objects_2d = read_objects(out / "2d" / f"{frame_id}.txt")
        record = json.loads((out / "labels" / f"{frame_id}.json").read_text())
        matched = [r for r in record["labels"] if r["provenance"] == "matched"]
        assert len(objects_2d) == len(matched)
        assert len(objects_3d) <= len(record["labels"])
        assert objects_3d.score is not None and (objects_3d.dimensions > 0).all()
        rows += len(objects_3d)
    assert rows > 0
    summary = json.loads((out / "labeling.json").read_text())
    assert summary["frames"] == len(ids) and summary["model_version"] == "000001"
    assert summary["thresholds"]["tau_hung"] == 50.0
    for modality in ("3d", "2d"):
        assert main(["eval", "--gt-dir", str(synth_root / "training" / "label_2"),
                     "--pred-dir", str(out / modality), "--ids-file",
                     str(synth_root / "ImageSets" / "val.txt"),
                     "--json", str(tmp_path / f"eval_{modality}.json")]) == 0  # fmt: skip
    assert "mAP moderate" in capsys.readouterr().out
    assert main(["label", "--repository", str(tmp_path / "none"), "--data", str(synth_root),
                 "--split", "val", "--out", str(out)]) == 2  # fmt: skip


def test_kitti_rows_are_those_of_the_pytorch_prediction_path(exported_repository, synth_root):
    """serving.offline's torch-free conversion writes what detmatch.inference writes."""
    labeler = Labeler.from_repository(exported_repository)
    frame = KittiDataset(synth_root).load_frame("000002", with_labels=False)
    result = labeler.label(frame.image, frame.points, frame.calib, tau_hung=50.0,
                           tau_3d_outside_view=0.1)  # fmt: skip
    labels = result.labels
    as_3d = Detections(labels.boxes_3d, labels.score_3d, labels.class_3d,
                       np.zeros((len(labels), 3)))  # fmt: skip
    matched = labels.matched
    as_2d = Detections(labels.boxes_2d[matched], labels.score_2d[matched],
                       labels.class_2d[matched], np.zeros((int(matched.sum()), 3)))  # fmt: skip
    for ours, theirs in (
        (labels_to_objects_3d(result, frame.calib),
         detections_3d_to_objects(as_3d, result.classes, frame.calib, frame.image_size)),
        (labels_to_objects_2d(result), detections_2d_to_objects(as_2d, result.classes)),
    ):  # fmt: skip
        assert len(ours) > 0 and list(ours.names) == list(theirs.names)
        for field in ("truncated", "occluded", "alpha", "bbox", "dimensions", "location",
                      "rotation_y", "score"):  # fmt: skip
            np.testing.assert_allclose(getattr(ours, field), getattr(theirs, field))
