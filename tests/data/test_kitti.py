import numpy as np
import pytest
from PIL import Image

from detmatch.data.kitti import (
    KittiDataset,
    KittiFormatError,
    format_objects,
    labels_to_objects,
    parse_objects,
    read_calib,
    read_calib_file,
    read_image,
    read_image_set,
    read_objects,
    read_points,
    write_calib,
    write_frame,
    write_image_set,
    write_objects,
)
from detmatch.geometry import points_in_boxes, project_boxes_to_image

SAMPLE_IDS = ["000000", "000001", "000002"]


def test_real_frames_project_onto_their_2d_boxes_and_contain_points(kitti_sample):
    dataset = KittiDataset(kitti_sample)
    checked = 0
    for frame_id in SAMPLE_IDS:
        frame = dataset.load_frame(frame_id)
        labels = frame.labels
        objects = (labels.names != "DontCare") & (labels.truncated < 0.01)
        projected = project_boxes_to_image(
            labels.boxes_3d.data[objects], frame.calib, frame.image_size
        )
        assert np.abs(projected - labels.boxes_2d.xyxy[objects]).max(initial=0.0) <= 10.0
        counts = points_in_boxes(frame.points, labels.boxes_3d.data[objects]).sum(axis=1)
        assert np.all(counts > 0), f"{frame_id}: a box without LiDAR points {counts}"
        checked += int(objects.sum())
    assert checked == 6  # Pedestrian; Truck, Car, Cyclist; Misc, Car


def test_label_files_round_trip_through_the_lidar_frame(kitti_sample, tmp_path):
    dataset = KittiDataset(kitti_sample)
    for frame_id in SAMPLE_IDS:
        original = dataset.read_objects(frame_id)
        calib = read_calib(dataset.calib_path(frame_id))
        labels = dataset.load_frame(frame_id).labels
        path = tmp_path / f"{frame_id}.txt"
        write_objects(path, labels_to_objects(labels, calib))
        again = read_objects(path)
        assert list(again.names) == list(original.names)
        for field in (
            "truncated",
            "occluded",
            "alpha",
            "bbox",
            "dimensions",
            "location",
            "rotation_y",
        ):
            np.testing.assert_allclose(getattr(again, field), getattr(original, field), atol=1e-9)
        # Our own output is a fixed point of read -> write.
        assert format_objects(read_objects(path)) == path.read_text()


def test_calib_points_and_image_round_trip(kitti_sample, tmp_path):
    dataset = KittiDataset(kitti_sample)
    calib_file = read_calib_file(dataset.calib_path("000001"))
    calib = read_calib(dataset.calib_path("000001"))
    write_calib(tmp_path / "calib.txt", calib, extra=calib_file)
    written = read_calib_file(tmp_path / "calib.txt")
    assert written.keys() == calib_file.keys()
    for key, value in calib_file.items():
        np.testing.assert_array_equal(written[key], value)

    frame = dataset.load_frame("000001")
    write_frame(tmp_path / "copy", frame)
    copy = KittiDataset(tmp_path / "copy")
    assert copy.ids() == ["000001"]
    again = copy.load_frame("000001")
    np.testing.assert_array_equal(again.image, frame.image)
    assert copy.points_path("000001").read_bytes() == dataset.points_path("000001").read_bytes()
    np.testing.assert_allclose(again.labels.boxes_3d.data, frame.labels.boxes_3d.data, atol=1e-9)


def test_result_files_carry_scores_and_placeholders():
    text = (
        "Car -1 -1 -10 10.00 20.00 110.00 80.00 -1 -1 -1 -1000 -1000 -1000 -10 0.9000\n"
        "Car 0 0 0.5 10 20 110 80 1.5 1.6 3.9 1.0 1.6 20.0 0.3 0.4\n"
    )
    objects = parse_objects(text)
    np.testing.assert_allclose(objects.score, [0.9, 0.4])
    assert objects.has_3d.tolist() == [False, True]
    assert parse_objects(format_objects(objects)).score.tolist() == [0.9, 0.4]


@pytest.mark.parametrize(
    ("text", "line", "problem"),
    [
        ("Car 0 0 0\n", 1, "expected 15 or 16 fields, found 4"),
        (
            "Car 0 0 0 1 2 3 4 1 1 1 1 1 1 0\nCar 0 0 0 1 2 3 4 1 1 1 1 1 1 0 0.5\n",
            2,
            "found 16 fields",
        ),
        ("Car 0 x 0 1 2 3 4 1 1 1 1 1 1 0\n", 1, "non-numeric field"),
        ("Car 0 0 nan 1 2 3 4 1 1 1 1 1 1 0\n", 1, "NaN or Inf"),
        ("Car 0 0.5 0 1 2 3 4 1 1 1 1 1 1 0\n", 1, "occluded must be an integer"),
    ],
)
def test_malformed_label_files_name_file_line_and_problem(tmp_path, text, line, problem):
    path = tmp_path / "000007.txt"
    path.write_text(text)
    with pytest.raises(KittiFormatError) as error:
        read_objects(path)
    assert error.value.line == line
    assert str(error.value).startswith(f"{path}:{line}: ")
    assert problem in str(error.value)


def test_malformed_calib_points_images_and_image_sets(kitti_sample, tmp_path):
    calib_text = (kitti_sample / "training" / "calib" / "000001.txt").read_text()
    short = tmp_path / "short.txt"
    short.write_text(calib_text.replace("R0_rect: 9.999239000000e-01 ", "R0_rect: "))
    with pytest.raises(KittiFormatError, match=r"short.txt:5: R0_rect needs 9 numbers, found 8"):
        read_calib(short)
    missing = tmp_path / "missing.txt"
    missing.write_text("".join(line + "\n" for line in calib_text.splitlines() if "P2" not in line))
    with pytest.raises(KittiFormatError, match="missing P2"):
        read_calib(missing)

    points = tmp_path / "points.bin"
    points.write_bytes(np.zeros(10, dtype=np.float32).tobytes())
    with pytest.raises(KittiFormatError, match="not a multiple of 16"):
        read_points(points)

    image = tmp_path / "image.png"
    image.write_bytes(b"not a png at all")
    with pytest.raises(KittiFormatError, match="cannot decode image"):
        read_image(image)

    image_set = tmp_path / "train.txt"
    image_set.write_text("000001\n../etc/passwd\n")
    with pytest.raises(KittiFormatError, match=r"train.txt:2: invalid frame id"):
        read_image_set(image_set)


def test_image_sets_and_frame_ids(tmp_path):
    write_image_set(tmp_path / "ImageSets" / "train.txt", ["000003", "000001"])
    assert read_image_set(tmp_path / "ImageSets" / "train.txt") == ["000003", "000001"]
    with pytest.raises(ValueError, match="invalid frame id"):
        write_image_set(tmp_path / "bad.txt", ["a/b"])
    (tmp_path / "training").mkdir()
    dataset = KittiDataset(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"no split 'val'.*available: \['train'\]"):
        dataset.ids("val")
    with pytest.raises(ValueError, match="invalid frame id"):
        dataset.image_path("../../secret")


def test_missing_layout_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no training/ directory"):
        KittiDataset(tmp_path)


def test_images_written_as_png(tmp_path, kitti_sample):
    frame = KittiDataset(kitti_sample).load_frame("000002")
    write_frame(tmp_path, frame)
    with Image.open(tmp_path / "training" / "image_2" / "000002.png") as image:
        assert image.format == "PNG" and image.size == frame.image_size
