"""A fast lossless PNG encoder for the images the label store keeps (raw and JPEG uploads).

Every row takes PNG's Sub filter (each byte minus the same channel of the pixel to its left,
one NumPy subtraction) and the filtered rows are Huffman-coded by zlib without string
matching. On KITTI frames that is about 4x faster than Pillow at zlib level 1 and a little
smaller (BENCHMARKS.md, issue 42): camera images are smooth left to right, so Sub leaves small
residuals that Huffman coding alone compresses well.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_SUB_FILTER = 1
_RGB8 = (8, 2, 0, 0, 0)  # bit depth, colour type RGB, deflate, adaptive filtering, no interlace


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_png(pixels: np.ndarray) -> bytes:
    """(H, W, 3) uint8 RGB -> PNG bytes that decode to exactly these pixels."""
    pixels = np.asarray(pixels)
    if pixels.ndim != 3 or pixels.shape[2] != 3 or pixels.dtype != np.uint8:
        raise ValueError(f"expected (H, W, 3) uint8 RGB pixels, got {pixels.shape} {pixels.dtype}")
    height, width, _ = pixels.shape
    if height == 0 or width == 0:
        raise ValueError(f"an image needs at least one pixel, got {width} x {height}")
    rows = pixels.reshape(height, width * 3)
    filtered = np.empty((height, width * 3 + 1), np.uint8)
    filtered[:, 0] = _SUB_FILTER
    filtered[:, 1:4] = rows[:, :3]
    np.subtract(rows[:, 3:], rows[:, :-3], out=filtered[:, 4:])  # wraps modulo 256, as PNG's
    compressor = zlib.compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_HUFFMAN_ONLY)
    data = compressor.compress(filtered) + compressor.flush()
    header = struct.pack(">II", width, height) + bytes(_RGB8)
    return PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", data) + _chunk(b"IEND", b"")
