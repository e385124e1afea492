"""The wire-format decoding and the domain error -> status code mapping, without a server."""

from __future__ import annotations

import grpc
import numpy as np
import pytest

from detmatch.data.kitti import KittiFormatError
from serving.decode import decode_calibration, decode_image, decode_points, encode_points
from serving.errors import (
    InputTooLarge,
    InvalidInput,
    ModelUnavailable,
    StoreError,
    status_for,
)


def test_points_round_trip_little_endian():
    points = np.arange(12, dtype=np.float32).reshape(3, 4)
    data = encode_points(points)
    assert data == points.astype("<f4").tobytes()
    np.testing.assert_array_equal(decode_points(data), points)
    with pytest.raises(InvalidInput, match="Inf"):
        decode_points(np.array([[0, 0, np.inf, 0]], "<f4").tobytes())


def test_calibration_sizes_are_checked():
    calib = decode_calibration([1.0] * 12, np.eye(3).ravel().tolist(), [0.0] * 12)
    assert calib.P2.shape == (3, 4)
    with pytest.raises(InvalidInput, match="calibration.r0_rect: expected 9 values, got 8"):
        decode_calibration([1.0] * 12, [0.0] * 8, [0.0] * 12)


def test_images_beyond_the_pixel_limit_are_resource_exhausted(monkeypatch):
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (30, 20)).save(buffer, format="PNG")
    assert decode_image(buffer.getvalue())[0].shape == (20, 30, 3)
    monkeypatch.setattr("serving.decode.MAX_IMAGE_PIXELS", 599)
    with pytest.raises(InputTooLarge, match="30 x 20 pixels exceeds"):
        decode_image(buffer.getvalue())


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (InvalidInput("points: x"), grpc.StatusCode.INVALID_ARGUMENT),
        (ValueError("tau_hung: x"), grpc.StatusCode.INVALID_ARGUMENT),
        (KittiFormatError("f", 1, "bad"), grpc.StatusCode.INVALID_ARGUMENT),
        (InputTooLarge("image: big"), grpc.StatusCode.RESOURCE_EXHAUSTED),
        (ModelUnavailable("none"), grpc.StatusCode.UNAVAILABLE),
        (StoreError("disk full"), grpc.StatusCode.UNAVAILABLE),
        (KeyError("bug"), grpc.StatusCode.INTERNAL),
    ],
)
def test_status_for(error, code):
    assert status_for(error)[0] == code
