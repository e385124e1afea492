"""A data set laid out as KITTI's object benchmark ships it: training/ with labels and
testing/ without, no ImageSets, some images JPEG; made from the three real sample frames."""

from __future__ import annotations

import shutil
from pathlib import Path

from PIL import Image

# Frames whose image_2 file is JPEG instead of PNG, per subset.
JPEG_FRAMES = {"training": ("000002",), "testing": ("000000",)}
TESTING_FRAMES = ("000000", "000001")


def make_stock_kitti(sample: Path, root: Path) -> Path:
    """root/training/ holds the sample's three frames with labels, root/testing/ two of them
    without; the frames named in JPEG_FRAMES have JPEG images."""
    for subset in ("training", "testing"):
        ids = ("000000", "000001", "000002") if subset == "training" else TESTING_FRAMES
        kinds = ("velodyne", "calib", "label_2") if subset == "training" else ("velodyne", "calib")
        for kind in (*kinds, "image_2"):
            (root / subset / kind).mkdir(parents=True, exist_ok=True)
        for frame_id in ids:
            for kind in kinds:
                suffix = ".bin" if kind == "velodyne" else ".txt"
                name = f"{frame_id}{suffix}"
                shutil.copy(sample / "training" / kind / name, root / subset / kind / name)
            source = sample / "training" / "image_2" / f"{frame_id}.png"
            if frame_id in JPEG_FRAMES[subset]:
                with Image.open(source) as image:
                    image.convert("RGB").save(
                        root / subset / "image_2" / f"{frame_id}.jpg", quality=95
                    )
            else:
                shutil.copy(source, root / subset / "image_2" / f"{frame_id}.png")
    return root
