import json

import numpy as np
from PIL import Image

from commands.main import main
from detmatch.data.kitti import KittiDataset, read_image_set, read_objects
from detmatch.inference import detections_2d_to_objects, detections_3d_to_objects
from detmatch.structures import Detections
from serving.labeler import Labeler
from serving.serialize import labels_to_objects_2d, labels_to_objects_3d
from serving.store import check_integrity, list_frames
from tests.stock_kitti import TESTING_FRAMES, make_stock_kitti


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


def _label_records(out, frame_id):
    return json.loads((out / "labels" / f"{frame_id}.json").read_text())["labels"]


def test_labeling_the_kitti_sample_as_shipped(exported_repository, kitti_sample, tmp_path, capsys):
    """Three real KITTI frames without ImageSets: `--all` labels every frame of training/, the
    same labels the labeler gives frame by frame, and `eval --all` scores them."""
    out = tmp_path / "labels"
    assert main(["label", "--repository", str(exported_repository), "--data", str(kitti_sample),
                 "--all", "--out", str(out), "--tau-hung", "50"]) == 0  # fmt: skip
    assert "labeled 3 frames with model version 000001" in capsys.readouterr().out
    summary = json.loads((out / "labeling.json").read_text())
    assert summary["frames"] == 3 and summary["subset"] == "training"
    assert summary["frames_selected"] == "all frames" and summary["split"] is None
    labeler = Labeler.from_repository(exported_repository)
    dataset = KittiDataset(kitti_sample)
    for frame_id in ("000000", "000001", "000002"):
        frame = dataset.load_frame(frame_id, with_labels=False)
        expected = labeler.label(frame.image, frame.points, frame.calib, tau_hung=50.0)
        records = _label_records(out, frame_id)
        assert len(records) == len(expected) > 0
        assert [r["class_3d"] for r in records] == [
            expected.classes[c] for c in expected.labels.class_3d
        ]
        assert (out / "3d" / f"{frame_id}.txt").is_file()
    for modality in ("3d", "2d"):
        assert main(["eval", "--gt-dir", str(kitti_sample / "training" / "label_2"),
                     "--pred-dir", str(out / modality), "--all"]) == 0  # fmt: skip
    assert "mAP moderate" in capsys.readouterr().out
    # ImageSets are not there: --split says how to choose frames instead.
    assert main(["label", "--repository", str(exported_repository), "--data", str(kitti_sample),
                 "--split", "val", "--out", str(tmp_path / "val")]) == 2  # fmt: skip
    assert "--all" in capsys.readouterr().err


def test_label_and_predict_read_testing_and_jpeg_frames(
    exported_repository, trained_checkpoint, kitti_sample, tmp_path
):
    stock = make_stock_kitti(kitti_sample, tmp_path / "kitti")
    out = tmp_path / "testing_labels"
    assert main(["label", "--repository", str(exported_repository), "--data", str(stock),
                 "--subset", "testing", "--all", "--out", str(out),
                 "--tau-hung", "50"]) == 0  # fmt: skip
    assert json.loads((out / "labeling.json").read_text())["subset"] == "testing"
    labeler = Labeler.from_repository(exported_repository)
    testing = KittiDataset(stock, "testing")
    assert testing.image_path("000000").suffix == ".jpg"
    for frame_id in TESTING_FRAMES:
        frame = testing.load_frame(frame_id)
        expected = labeler.label(frame.image, frame.points, frame.calib, tau_hung=50.0)
        assert len(_label_records(out, frame_id)) == len(expected) > 0
    assert sorted(p.stem for p in (out / "labels").iterdir()) == list(TESTING_FRAMES)

    ids_file = tmp_path / "ids.txt"
    ids_file.write_text("000002\n")  # training/'s JPEG frame
    predicted = tmp_path / "predicted"
    assert main(["predict", "--checkpoint", str(trained_checkpoint), "--data", str(stock),
                 "--ids-file", str(ids_file), "--out", str(predicted)]) == 0  # fmt: skip
    assert [p.name for p in (predicted / "3d").iterdir()] == ["000002.txt"]
    assert [p.name for p in (predicted / "2d").iterdir()] == ["000002.txt"]
    read_objects(predicted / "3d" / "000002.txt")

    # A data set holding only testing/ is read without --subset.
    (stock / "training").rename(tmp_path / "training_elsewhere")
    only = tmp_path / "only_testing"
    assert main(["label", "--repository", str(exported_repository), "--data", str(stock),
                 "--all", "--out", str(only)]) == 0  # fmt: skip
    assert json.loads((only / "labeling.json").read_text())["subset"] == "testing"


def test_label_into_the_store_as_the_service_stores(
    exported_repository, kitti_sample, tmp_path, capsys
):
    """`detmatch label --store`: every frame and its labels go into the label store (a JPEG
    frame as PNG of the same pixels), the stored label rows are the --out files' rows, and
    running it again stores nothing twice."""
    stock = make_stock_kitti(kitti_sample, tmp_path / "kitti")
    store, out = tmp_path / "store", tmp_path / "labels"
    args = ["label", "--repository", str(exported_repository), "--data", str(stock), "--all",
            "--store", str(store)]  # fmt: skip
    assert main([*args, "--out", str(out), "--shard", "batch-1"]) == 0
    assert "(3 frames stored, 0 already there)" in capsys.readouterr().out
    records = list_frames(store)
    assert [(r.frame_id, r.shard, r.model_version) for r in records] == [
        (i, "batch-1", "000001") for i in ("000000", "000001", "000002")
    ]
    assert check_integrity(store) == []
    stored = store / "shards" / "batch-1" / "namespaces" / "default" / "training"
    dataset = KittiDataset(stock)
    assert dataset.image_path("000002").suffix == ".jpg"
    for frame_id in ("000000", "000001", "000002"):
        assert (stored / "label_2" / f"{frame_id}.txt").read_text() == (
            out / "3d" / f"{frame_id}.txt"
        ).read_text()
        pixels = np.asarray(Image.open(stored / "image_2" / f"{frame_id}.png").convert("RGB"))
        np.testing.assert_array_equal(pixels, dataset.load_frame(frame_id).image)
        assert (stored / "velodyne" / f"{frame_id}.bin").read_bytes() == (
            dataset.points_path(frame_id).read_bytes()
        )
    summary = json.loads((out / "labeling.json").read_text())
    assert summary["store"]["shard"] == "batch-1" and summary["stored"] == 3

    # Without --out; the frames are there already, so nothing is written twice.
    assert main([*args, "--shard", "batch-1"]) == 0
    assert "(0 frames stored, 3 already there)" in capsys.readouterr().out
    assert len(list_frames(store)) == 3
    assert main(["label", "--repository", str(exported_repository), "--data", str(stock),
                 "--all"]) == 2  # fmt: skip
    assert "give --out DIR" in capsys.readouterr().err


def test_label_into_a_shard_another_process_holds_is_a_clear_error(
    exported_repository, synth_root, tmp_path, capsys
):
    from serving.store import LabelStore

    held = LabelStore(tmp_path / "store", "offline")  # as a running server holds its shard
    try:
        argv = ["label", "--repository", str(exported_repository), "--data", str(synth_root),
                "--split", "val", "--store", str(tmp_path / "store")]  # fmt: skip
        assert main(argv) == 2
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and "--shard offline" in error and "another process" in error
    finally:
        held.close()
