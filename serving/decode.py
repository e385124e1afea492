"""Wire formats of docs/design.md §7 -> the labeler's arrays, with errors naming the field.

Images: PNG or JPEG bytes, or raw RGB pixels (a view, no decode) -> (H, W, 3) uint8 RGB.
Points: raw little-endian float32 bytes, N x 4 (x, y, z, intensity) -> (N, 4) float32.
Calibration: P2 (12), R0_rect (9), Tr_velo_to_cam (12) row-major doubles -> Calibration,
refused when a matrix cannot be a camera projection or a rigid transform. Frame ids and
namespaces: 1-64 letters, digits, '_' or '-'. Every error is `InvalidInput` whose message
starts with the field's name, and never echoes more than a short excerpt of what the client
sent.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Sequence

import numpy as np
from PIL import Image

try:  # the fast path of 8-bit RGB PNGs; Pillow decodes everything without it
    import pyspng as _spng
except ImportError:  # pragma: no cover - pyspng is in the serve extra
    _spng = None

from detmatch.data.kitti import FRAME_ID_PATTERN
from detmatch.structures import Calibration
from serving.errors import InvalidInput

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"
# Decompression-bomb guard, checked on the header before any pixel is decoded: 4K UHD
# (3840 x 2160), 18x a KITTI frame (1242 x 375) and 3.4x a Waymo front camera (1920 x 1280).
DEFAULT_MAX_IMAGE_PIXELS = 3840 * 2160
# LiDAR points per frame: 17x a 64-beam sweep (KITTI's HDL-64E: about 120,000), 32 MB of wire.
DEFAULT_MAX_POINTS = 2_000_000
CALIBRATION_SIZES = {"p2": 12, "r0_rect": 9, "tr_velo_to_cam": 12}
# No real calibration holds a value this large (KITTI's largest is P2's focal length, ~721).
MAX_CALIBRATION_VALUE = 1e6
# A matrix whose smallest singular value is below this fraction of its largest is singular.
MIN_SINGULAR_RATIO = 1e-9
# R0_rect and Tr_velo_to_cam's left 3 x 3 must be rotations to this tolerance (KITTI's files
# print six decimals, so theirs are orthonormal to about 1e-6).
ROTATION_TOLERANCE = 1e-2
DEFAULT_NAMESPACE = "default"
EXCERPT_CHARS = 64


def excerpt(value: str, limit: int = EXCERPT_CHARS) -> str:
    """repr(value), cut to `limit` characters with the full length said: errors never echo a
    whole hostile field (a 16 KB id would not fit in a gRPC status)."""
    if len(value) <= limit:
        return repr(value)
    return f"{value[:limit]!r}... ({len(value)} characters)"


def decode_id(value: str, field: str) -> str:
    """A frame id or namespace: 1-64 letters, digits, '_' or '-' (a file name stem)."""
    if isinstance(value, str) and FRAME_ID_PATTERN.match(value):
        return value
    shown = excerpt(value) if isinstance(value, str) else type(value).__name__
    raise InvalidInput(f"{field}: invalid {field.replace('_', ' ')} {shown}: use 1-64 "
                       "letters, digits, '_' or '-'")  # fmt: skip


def decode_frame_id(frame_id: str) -> str:
    return decode_id(frame_id, "frame_id")


def decode_namespace(namespace: str | None) -> str:
    """The key's data-set namespace; empty or None is DEFAULT_NAMESPACE."""
    if not namespace:
        return DEFAULT_NAMESPACE
    namespace = decode_id(namespace, "namespace")
    if namespace.startswith("-"):  # a directory named -rf is a trap for shell tools
        raise InvalidInput(f"namespace: {namespace!r} starts with '-'")
    return namespace


def decode_image(data: bytes, max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS) -> tuple[np.ndarray, str]:
    """PNG or JPEG bytes -> ((H, W, 3) uint8 RGB, 'png' or 'jpeg'). The header's size is
    checked against max_pixels before anything is decoded."""
    if not data:
        raise InvalidInput("image: empty; send PNG or JPEG bytes (or the pixels as raw_image)")
    if data.startswith(PNG_MAGIC):
        kind = "png"
    elif data.startswith(JPEG_MAGIC):
        kind = "jpeg"
    else:
        raise InvalidInput(f"image: not PNG or JPEG (first bytes {data[:8].hex()})")
    if kind == "png" and len(data) >= 24 and data[12:16] == b"IHDR":  # before Pillow's limit
        _check_pixels(*struct.unpack(">II", data[16:24]), max_pixels)
        if len(data) >= 29 and data[24:26] == b"\x08\x02" and _spng is not None:
            pixels = _decode_rgb8_png(data)  # 8-bit RGB, what cameras write: libspng
            if pixels is not None:
                return pixels, kind
    try:
        with Image.open(io.BytesIO(data), formats=(kind.upper(),)) as image:
            _check_pixels(*image.size, max_pixels)  # the header's, nothing decoded yet
            pixels = np.asarray(image.convert("RGB"))
    except InvalidInput:
        raise
    except MemoryError:
        raise
    except Image.DecompressionBombError:
        raise InvalidInput(
            f"image: its header declares more pixels than the limit of {max_pixels}"
        ) from None
    except Exception:  # noqa: BLE001 - any failure to decode client bytes is bad input
        # Pillow's text would name its own objects ("<_io.BytesIO object at 0x...>"): ours.
        raise InvalidInput(
            f"image: cannot decode {kind.upper()} data (corrupt, truncated or a zero-sized image)"
        ) from None
    if pixels.ndim != 3 or pixels.shape[0] < 1 or pixels.shape[1] < 1:
        raise InvalidInput(f"image: empty image of shape {pixels.shape}")
    return pixels, kind


def decode_raw_image(
    width: int, height: int, data: bytes, max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
) -> np.ndarray:
    """Uncompressed 8-bit RGB, height x width x 3 bytes -> (H, W, 3) uint8, a read-only view of
    data (nothing decoded or copied)."""
    if width < 1 or height < 1:
        raise InvalidInput(f"raw_image: {width} x {height} pixels; width and height must be >= 1")
    _check_pixels(width, height, max_pixels)
    if len(data) != width * height * 3:
        raise InvalidInput(f"raw_image: rgb holds {len(data)} bytes; {width} x {height} RGB "
                           f"pixels are {width * height * 3}")  # fmt: skip
    return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3)


def _decode_rgb8_png(data: bytes) -> np.ndarray | None:
    """An 8-bit RGB PNG decoded by libspng (pyspng): the same pixels as Pillow's, about 30 %
    faster (BENCHMARKS.md, issue 42); None when libspng refuses it (Pillow then decodes it,
    or names what is wrong)."""
    try:
        pixels = _spng.load(data)
    except Exception:  # noqa: BLE001 - Pillow decides what a bad file is
        return None
    if pixels.ndim != 3 or pixels.shape[2] != 3 or pixels.dtype != np.uint8:
        return None
    return pixels


def _check_pixels(width: int, height: int, max_pixels: int) -> None:
    if width * height > max_pixels:
        raise InvalidInput(
            f"image: {width} x {height} pixels ({width * height}) exceeds the limit of "
            f"{max_pixels} pixels"
        )


def decode_points(data: bytes, max_points: int = DEFAULT_MAX_POINTS) -> np.ndarray:
    """Little-endian float32 bytes, N x 4 -> (N, 4) float32 (a read-only view of data), every
    value finite, N at most max_points."""
    if not data:
        raise InvalidInput("points: empty point cloud; send N x 4 little-endian float32")
    if len(data) % 16:
        raise InvalidInput(
            f"points: {len(data)} bytes is not a multiple of 16 (N x 4 float32 values)"
        )
    if len(data) // 16 > max_points:
        raise InvalidInput(
            f"points: {len(data) // 16} points exceeds the limit of {max_points} points per frame"
        )
    # A read-only view of the request's bytes, no copy (a byte-swapped one on a big-endian host).
    points = np.frombuffer(data, dtype="<f4").reshape(-1, 4).astype(np.float32, copy=False)
    with np.errstate(all="ignore"):  # one sum is finite only if every value is (or overflows)
        finite_sum = bool(np.isfinite(points.sum()))
    if not finite_sum and not np.isfinite(points).all():
        bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
        raise InvalidInput(
            f"points: {len(bad)} of {len(points)} points hold NaN or Inf (first at row {bad[0]})"
        )
    return points


def decode_calibration(
    p2: Sequence[float], r0_rect: Sequence[float], tr_velo_to_cam: Sequence[float]
) -> Calibration:
    """Row-major P2 (12), R0_rect (9), Tr_velo_to_cam (12) -> Calibration.

    Refused (InvalidInput naming the matrix): a wrong number of values, NaN or Inf, a value
    beyond MAX_CALIBRATION_VALUE, a P2 whose left 3 x 3 block is singular (it cannot project),
    an R0_rect or a Tr_velo_to_cam rotation that is not a rotation (ROTATION_TOLERANCE)."""
    given = {"p2": p2, "r0_rect": r0_rect, "tr_velo_to_cam": tr_velo_to_cam}
    matrices = {}
    for name, expected in CALIBRATION_SIZES.items():
        got = len(given[name])
        if got != expected:
            raise InvalidInput(f"calibration.{name}: expected {expected} values, got {got}")
        values = np.asarray(given[name], np.float64)
        if not np.isfinite(values).all():
            raise InvalidInput(f"calibration.{name}: holds NaN or Inf")
        largest = float(np.abs(values).max())
        if largest > MAX_CALIBRATION_VALUE:
            raise InvalidInput(
                f"calibration.{name}: a value of magnitude {largest:.3g} is beyond "
                f"{MAX_CALIBRATION_VALUE:.0e}; not a calibration"
            )
        matrices[name] = values.reshape(3, -1)
    singular = np.linalg.svd(matrices["p2"][:, :3], compute_uv=False)
    if singular[0] == 0.0 or singular[-1] < MIN_SINGULAR_RATIO * singular[0]:
        raise InvalidInput(
            "calibration.p2: rank-deficient (its left 3 x 3 block is singular, singular values "
            f"{', '.join(f'{s:.3g}' for s in singular)}); it cannot project points"
        )
    _check_rotation("r0_rect", matrices["r0_rect"])
    _check_rotation("tr_velo_to_cam", matrices["tr_velo_to_cam"][:, :3])
    return Calibration(matrices["p2"], matrices["r0_rect"], matrices["tr_velo_to_cam"])


def _check_rotation(name: str, rotation: np.ndarray) -> None:
    error = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
    determinant = float(np.linalg.det(rotation))
    if error > ROTATION_TOLERANCE or determinant <= 0:
        what = "rotation" if name == "r0_rect" else "rotation part (left 3 x 3)"
        raise InvalidInput(
            f"calibration.{name}: its {what} is not a rotation (|R R^T - I| = {error:.3g}, "
            f"det {determinant:.3g}); rank-deficient or degenerate"
        )


def encode_points(points: np.ndarray) -> bytes:
    """(N, 4) points -> the wire's little-endian float32 bytes."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must be (N, 4), got {points.shape}")
    return points.astype("<f4").tobytes()
