import numpy as np
from PIL import Image

from commands.main import main
from detmatch.data.kitti import KittiDataset
from detmatch.data.visualize import CLASS_COLOURS


def test_show_draws_the_image_boxes_and_bev(kitti_sample, tmp_path):
    out = tmp_path / "frame.png"
    assert main(["show", "--data", str(kitti_sample), "--frame", "000001", "--out", str(out)]) == 0
    frame = KittiDataset(kitti_sample).load_frame("000001")
    with Image.open(out) as picture:
        pixels = np.asarray(picture.convert("RGB"))
    width, height = frame.image_size
    assert pixels.shape[1] == width and pixels.shape[0] > height + width
    # The car's 2D box edge is drawn in the Car colour on top of the image.
    x1, y1, x2, y2 = frame.labels.boxes_2d.xyxy[frame.labels.names == "Car"][0].astype(int)
    edge = pixels[(y1 + y2) // 2, x1 - 1 : x1 + 3]
    assert CLASS_COLOURS["Car"] in [tuple(p) for p in edge]
    # The bird's-eye view shows LiDAR points: many non-background pixels.
    bev = pixels[height + 18 :]
    assert (np.abs(bev.astype(int) - 16).sum(axis=2) > 0).mean() > 0.01


def test_show_overlays_predictions(kitti_sample, tmp_path):
    predictions = tmp_path / "pred"
    predictions.mkdir()
    label = (kitti_sample / "training" / "label_2" / "000002.txt").read_text().splitlines()[1]
    (predictions / "000002.txt").write_text(label + " 0.87\n")
    out = tmp_path / "frame.png"
    args = ["show", "--data", str(kitti_sample), "--frame", "000002", "--out", str(out)]
    assert main([*args, "--predictions", str(predictions)]) == 0
    assert out.stat().st_size > 0


def test_show_unknown_frame_is_a_clear_error(kitti_sample, tmp_path, capsys):
    out = tmp_path / "x.png"
    assert main(["show", "--data", str(kitti_sample), "--frame", "999999", "--out", str(out)]) == 2
    assert "999999" in capsys.readouterr().err
    assert not out.exists()
