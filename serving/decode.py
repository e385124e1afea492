"""Wire formats of DESIGN.md §7 -> the labeler's arrays, with errors naming the field.

Images: PNG or JPEG bytes -> (H, W, 3) uint8 RGB. Points: raw little-endian float32 bytes,
N x 4 (x, y, z, intensity) -> (N, 4) float32. Calibration: P2 (12), R0_rect (9),
Tr_velo_to_cam (12) row-major doubles -> Calibration.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np
from PIL import Image

from detmatch.data.kitti import validate_frame_id
from detmatch.structures import Calibration
from serving.errors import InputTooLarge, InvalidInput

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"
# Decompression-bomb guard: far above a KITTI frame (1242 x 375) or a 4K camera.
MAX_IMAGE_PIXELS = 8192 * 8192
CALIBRATION_SIZES = {"p2": 12, "r0_rect": 9, "tr_velo_to_cam": 12}


def decode_frame_id(frame_id: str) -> str:
    try:
        return validate_frame_id(frame_id)
    except ValueError as error:
        raise InvalidInput(f"frame_id: {error}") from None


def decode_image(data: bytes) -> tuple[np.ndarray, str]:
    """PNG or JPEG bytes -> ((H, W, 3) uint8 RGB, 'png' or 'jpeg')."""
    if not data:
        raise InvalidInput("image: empty; send PNG or JPEG bytes")
    if data.startswith(PNG_MAGIC):
        kind = "png"
    elif data.startswith(JPEG_MAGIC):
        kind = "jpeg"
    else:
        raise InvalidInput(f"image: not PNG or JPEG (first bytes {data[:8].hex()})")
    try:
        with Image.open(io.BytesIO(data)) as image:
            width, height = image.size
            if width * height > MAX_IMAGE_PIXELS:
                raise InputTooLarge(
                    f"image: {width} x {height} pixels exceeds the limit of {MAX_IMAGE_PIXELS}"
                )
            pixels = np.asarray(image.convert("RGB"))
    except InputTooLarge:
        raise
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
        raise InvalidInput(f"image: cannot decode {kind.upper()} data: {error}") from None
    if pixels.shape[0] < 1 or pixels.shape[1] < 1:
        raise InvalidInput(f"image: empty image of shape {pixels.shape}")
    return pixels, kind


def decode_points(data: bytes) -> np.ndarray:
    """Little-endian float32 bytes, N x 4 -> (N, 4) float32, every value finite."""
    if not data:
        raise InvalidInput("points: empty point cloud; send N x 4 little-endian float32")
    if len(data) % 16:
        raise InvalidInput(
            f"points: {len(data)} bytes is not a multiple of 16 (N x 4 float32 values)"
        )
    points = np.frombuffer(data, dtype="<f4").reshape(-1, 4).astype(np.float32)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InvalidInput(
            f"points: {len(bad)} of {len(points)} points hold NaN or Inf (first at row {bad[0]})"
        )
    return points


def decode_calibration(
    p2: Sequence[float], r0_rect: Sequence[float], tr_velo_to_cam: Sequence[float]
) -> Calibration:
    """Row-major P2 (12), R0_rect (9), Tr_velo_to_cam (12) -> Calibration."""
    values = {"p2": p2, "r0_rect": r0_rect, "tr_velo_to_cam": tr_velo_to_cam}
    for name, expected in CALIBRATION_SIZES.items():
        got = len(values[name])
        if got != expected:
            raise InvalidInput(f"calibration.{name}: expected {expected} values, got {got}")
        if not all(math.isfinite(v) for v in values[name]):
            raise InvalidInput(f"calibration.{name}: holds NaN or Inf")
    try:
        return Calibration.from_flat(
            np.asarray(p2, np.float64),
            np.asarray(r0_rect, np.float64),
            np.asarray(tr_velo_to_cam, np.float64),
        )
    except ValueError as error:
        raise InvalidInput(f"calibration: {error}") from None


def encode_points(points: np.ndarray) -> bytes:
    """(N, 4) points -> the wire's little-endian float32 bytes."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must be (N, 4), got {points.shape}")
    return points.astype("<f4").tobytes()
