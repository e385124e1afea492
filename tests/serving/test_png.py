"""The store's PNG encoder: lossless for any RGB image with either deflate (Pillow's and
libspng's decoders read back exactly the pixels), and it refuses what is not 8-bit RGB."""

from __future__ import annotations

import io

import numpy as np
import pyspng
import pytest
from PIL import Image

import serving.png
from serving.png import encode_png
from tests.conftest import KITTI_SAMPLE


@pytest.fixture(autouse=True, params=["isal", "zlib"])
def deflate(request, monkeypatch):
    """Every test with ISA-L's deflate and with zlib's, the encoder's fallback."""
    if request.param == "zlib":
        monkeypatch.setattr(serving.png, "_isal", None)
    else:
        assert serving.png._isal is not None, "isal is in the serve extra"
    return request.param


def _decoded(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as image:
        image.verify()  # chunk CRCs and structure
    with Image.open(io.BytesIO(data)) as image:
        assert (image.mode, image.format) == ("RGB", "PNG")
        pixels = np.asarray(image)
    np.testing.assert_array_equal(pyspng.load(data), pixels)
    return pixels


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (3, 2), (64, 97)])
def test_random_pixels_come_back_exactly(shape):
    pixels = np.random.default_rng(sum(shape)).integers(0, 256, (*shape, 3), dtype=np.uint8)
    np.testing.assert_array_equal(_decoded(encode_png(pixels)), pixels)


def test_camera_frames_come_back_exactly_and_smaller_than_raw():
    for i in range(3):
        with Image.open(KITTI_SAMPLE / "training" / "image_2" / f"00000{i}.png") as image:
            pixels = np.asarray(image.convert("RGB"))
        data = encode_png(pixels)
        np.testing.assert_array_equal(_decoded(data), pixels)
        assert len(data) < 0.75 * pixels.nbytes


def test_views_are_encoded_as_their_pixels():
    pixels = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    for view in (pixels[::2, ::3], pixels[:, ::-1], pixels[2:9, 4:20]):
        np.testing.assert_array_equal(_decoded(encode_png(view)), view)


@pytest.mark.parametrize(
    "pixels",
    [
        np.zeros((4, 4), np.uint8),
        np.zeros((4, 4, 4), np.uint8),
        np.zeros((4, 4, 3), np.float32),
        np.zeros((0, 4, 3), np.uint8),
    ],
)
def test_what_is_not_8_bit_rgb_is_refused(pixels):
    with pytest.raises(ValueError, match="pixel"):
        encode_png(pixels)
