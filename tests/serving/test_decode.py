"""The wire-format decoding and the domain error -> status code mapping, without a server."""

from __future__ import annotations

import io
import re

import grpc
import numpy as np
import pytest
from PIL import Image

from detmatch.data.kitti import KittiFormatError
from serving.decode import (
    DEFAULT_MAX_IMAGE_PIXELS,
    decode_calibration,
    decode_frame_id,
    decode_image,
    decode_namespace,
    decode_points,
    decode_raw_image,
    encode_points,
)
from serving.errors import (
    InputTooLarge,
    InvalidInput,
    ModelUnavailable,
    StoreError,
    status_for,
)
from serving.request import RawImage
from tests.conftest import KITTI_SAMPLE


def test_points_round_trip_little_endian():
    points = np.arange(12, dtype=np.float32).reshape(3, 4)
    data = encode_points(points)
    assert data == points.astype("<f4").tobytes()
    np.testing.assert_array_equal(decode_points(data), points)
    with pytest.raises(InvalidInput, match="Inf"):
        decode_points(np.array([[0, 0, np.inf, 0]], "<f4").tobytes())


def _kitti_calibration() -> dict[str, list[float]]:
    from detmatch.data.kitti import read_calib

    calib = read_calib(KITTI_SAMPLE / "training" / "calib" / "000000.txt")
    return {"p2": calib.P2.ravel().tolist(), "r0_rect": calib.R0_rect.ravel().tolist(),
            "tr_velo_to_cam": calib.Tr_velo_to_cam.ravel().tolist()}  # fmt: skip


def test_calibration_sizes_are_checked():
    values = _kitti_calibration()
    calib = decode_calibration(**values)
    assert calib.P2.shape == (3, 4)
    with pytest.raises(InvalidInput, match="calibration.r0_rect: expected 9 values, got 8"):
        decode_calibration(**{**values, "r0_rect": [0.0] * 8})


def _degenerate() -> dict[str, tuple[str, dict]]:
    values = _kitti_calibration()
    p2 = np.asarray(values["p2"]).reshape(3, 4)
    rank_2 = p2.copy()
    rank_2[2, :3] = rank_2[0, :3]
    scaled_rotation = np.asarray(values["r0_rect"]) * 3.0
    return {
        "all-zero P2": ("calibration.p2: rank-deficient", {"p2": [0.0] * 12}),
        "all-zero R0_rect": ("calibration.r0_rect", {"r0_rect": [0.0] * 9}),
        "all-zero Tr": ("calibration.tr_velo_to_cam", {"tr_velo_to_cam": [0.0] * 12}),
        "rank-2 P2": ("calibration.p2: rank-deficient", {"p2": rank_2.ravel().tolist()}),
        "1e308 in P2": ("calibration.p2: a value of magnitude 1e+308", {"p2": [1e308] * 12}),
        "1e300 in Tr": ("calibration.tr_velo_to_cam", {"tr_velo_to_cam": [1e300] + [0.0] * 11}),
        "scaled R0_rect": (
            "calibration.r0_rect: its rotation is not a rotation",
            {"r0_rect": scaled_rotation.tolist()},
        ),  # fmt: skip
        "reflection in Tr": (
            "calibration.tr_velo_to_cam",
            {"tr_velo_to_cam": (np.diag([1.0, 1.0, -1.0, 0.0])[:3].ravel().tolist())},
        ),  # fmt: skip
        "NaN in R0": ("calibration.r0_rect: holds NaN", {"r0_rect": [float("nan")] * 9}),
    }


@pytest.mark.parametrize("case", sorted(_degenerate()))
def test_degenerate_calibrations_are_refused_naming_the_matrix(case):
    """All-zero, rank-deficient, absurd (1e308) or non-rigid matrices cannot be a camera and a
    LiDAR mount; they were accepted (and stored) before."""
    message, change = _degenerate()[case]
    with pytest.raises(InvalidInput, match=re.escape(message)):
        decode_calibration(**{**_kitti_calibration(), **change})


def test_the_synthetic_calibrations_are_accepted(synth_root):
    from detmatch.data.kitti import KittiDataset

    dataset = KittiDataset(synth_root)
    for frame_id in dataset.ids():
        calib = dataset.load_frame(frame_id, with_labels=False).calib
        decode_calibration(calib.P2.ravel(), calib.R0_rect.ravel(), calib.Tr_velo_to_cam.ravel())


def _png(width: int, height: int, mode: str = "RGB") -> bytes:
    buffer = io.BytesIO()
    Image.new(mode, (width, height)).save(buffer, format="PNG")
    return buffer.getvalue()


def test_an_image_over_the_pixel_limit_is_refused_before_decoding(monkeypatch):
    """The header's size is checked first: a 100 KB PNG that would decode to 8192 x 8192
    (a 200 MB array) is INVALID_ARGUMENT naming its size, and nothing is decoded."""
    assert decode_image(_png(30, 20), max_pixels=600)[0].shape == (20, 30, 3)
    with pytest.raises(InvalidInput, match="image: 30 x 20 pixels .* exceeds the limit of 599"):
        decode_image(_png(30, 20), max_pixels=599)
    bomb = _png(8192, 8192, "L")
    assert len(bomb) < 200_000
    decoded = []
    monkeypatch.setattr(Image.Image, "load", lambda self: decoded.append(self) or None)
    with pytest.raises(InvalidInput, match="image: 8192 x 8192 pixels") as caught:
        decode_image(bomb)
    assert decoded == []
    assert status_for(caught.value)[0] == grpc.StatusCode.INVALID_ARGUMENT
    assert DEFAULT_MAX_IMAGE_PIXELS >= 2 * 1920 * 1280  # KITTI and Waymo fit comfortably


@pytest.mark.parametrize("mode", ["I;16", "P", "LA", "RGBA", "1", "CMYK"])
def test_odd_image_modes_decode_to_rgb_or_are_refused(mode):
    image = Image.new(mode, (8, 6))
    buffer = io.BytesIO()
    kind = "JPEG" if mode == "CMYK" else "PNG"
    image.save(buffer, format=kind)
    pixels, _ = decode_image(buffer.getvalue())
    assert pixels.shape == (6, 8, 3) and pixels.dtype == np.uint8


def _saved_png(image: Image.Image, **options) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", **options)
    return buffer.getvalue()


def test_the_fast_png_path_gives_pillows_pixels():
    """8-bit RGB PNGs decode through libspng: the same pixels as Pillow on the KITTI frames,
    on noise, interlaced, with a transparency colour and with a gamma chunk; other PNGs go
    through Pillow as before."""
    import serving.decode as decode

    assert decode._spng is not None  # the serve extra installs it
    rng = np.random.default_rng(0)
    noise = Image.fromarray(rng.integers(0, 256, (37, 53, 3), dtype=np.uint8))
    cases = [
        (KITTI_SAMPLE / "training" / "image_2" / f"00000{i}.png").read_bytes() for i in range(3)
    ]
    cases += [_saved_png(noise), _saved_png(noise, interlace=1),
              _saved_png(noise, transparency=(0, 0, 0)), _saved_png(noise, gamma=0.5)]  # fmt: skip
    for data in cases:
        reference = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
        pixels, kind = decode_image(data)
        assert kind == "png" and pixels.dtype == np.uint8
        assert np.array_equal(pixels, reference)
    assert decode._decode_rgb8_png(cases[0]) is not None  # the fast path ran on a camera frame


def test_long_ids_are_cut_in_errors():
    """A 16 KB frame id was echoed whole: the status then exceeded gRPC's limit and the client
    got 'Stream removed' instead of INVALID_ARGUMENT."""
    with pytest.raises(InvalidInput) as caught:
        decode_frame_id("x" * 16384)
    message = str(caught.value)
    assert message.startswith("frame_id: invalid frame id 'xxx")
    assert "(16384 characters)" in message and len(message) < 300
    with pytest.raises(InvalidInput, match="namespace: invalid namespace"):
        decode_namespace("a/b")
    assert decode_namespace("") == decode_namespace(None) == "default"


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


def _png_header(width: int, height: int) -> bytes:
    """A PNG signature and IHDR chunk declaring width x height (no pixel data follows)."""
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk
            + struct.pack(">I", zlib.crc32(chunk)))  # fmt: skip


@pytest.mark.parametrize(
    "data, expected",
    [
        # Pillow's own words would be "cannot identify image file <_io.BytesIO object at 0x...>"
        (_png_header(0, 1), "image: cannot decode PNG data (corrupt, truncated or a zero-sized"),
        # and "DecompressionBombError: Image size (900000000 pixels) exceeds limit ..."
        (_png_header(30000, 30000), "image: 30000 x 30000 pixels (900000000) exceeds the limit"),
        (b"\xff\xd8\xff" + b"\x00" * 40, "image: cannot decode JPEG data"),
    ],
)
def test_image_errors_are_ours_naming_the_field_and_limit(data, expected):
    with pytest.raises(InvalidInput) as caught:
        decode_image(data)
    message = str(caught.value)
    assert message.startswith(expected)
    assert "object at 0x" not in message and "Error" not in message


def test_a_namespace_cannot_start_with_a_dash():
    from serving.store import validate_namespace

    with pytest.raises(InvalidInput, match="namespace: '-rf' starts with '-'"):
        decode_namespace("-rf")
    with pytest.raises(ValueError, match="invalid namespace '-rf': it starts with '-'"):
        validate_namespace("-rf")
    assert decode_namespace("drive-2024") == "drive-2024" == validate_namespace("drive-2024")


def test_raw_pixels_are_a_view_of_the_bytes_as_sent():
    pixels = np.random.default_rng(3).integers(0, 256, (375, 1242, 3), dtype=np.uint8)
    raw = RawImage.from_pixels(pixels)
    decoded = decode_raw_image(raw.width, raw.height, raw.rgb)
    np.testing.assert_array_equal(decoded, pixels)
    assert not decoded.flags.writeable  # a view of the request's bytes, nothing copied
    assert np.shares_memory(decoded, np.frombuffer(raw.rgb, dtype=np.uint8))
    with pytest.raises(InvalidInput, match="raw_image: rgb holds 11 bytes; 2 x 2 RGB pixels"):
        decode_raw_image(2, 2, b"\0" * 11)
    with pytest.raises(InvalidInput, match="exceeds the limit of 4 pixels"):
        decode_raw_image(3, 2, b"\0" * 18, max_pixels=4)
    with pytest.raises(ValueError, match=r"expected \(H, W, 3\) uint8 RGB"):
        RawImage.from_pixels(pixels.astype(np.float32))
