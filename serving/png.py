"""A fast lossless PNG encoder for the images the label store keeps (raw and JPEG uploads).

Every row takes PNG's Sub filter (each byte minus the same channel of the pixel to its left,
one NumPy subtraction): camera images are smooth left to right, so Sub leaves small residuals
that deflate's fastest settings compress well. The deflate is ISA-L's level 1 (the `isal`
package, AVX-512 where the CPU has it), or, without it, zlib's Huffman-only coding. On KITTI
frames (BENCHMARKS.md, issue 42): Pillow at zlib level 1 64 ms and 820 KB; Sub + zlib
Huffman-only 13 ms and 795 KB; Sub + ISA-L 5 ms and 814 KB. Both are lossless; the bytes differ.
The libraries' own encoders with the same fast settings are slower: imagecodecs' libpng with
the Sub filter and Huffman-only or RLE coding, 16-17 ms; Pillow has no filter choice. What is
written here is only PNG's container (three chunks); the compression is the library's.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from serving.decode import PNG_MAGIC

try:  # ISA-L's deflate; zlib's Huffman-only coding without it
    from isal import isal_zlib as _isal
except ImportError:  # pragma: no cover - isal is in the serve extra
    _isal = None

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
    data = _deflate(filtered)
    header = struct.pack(">II", width, height) + bytes(_RGB8)
    return PNG_MAGIC + _chunk(b"IHDR", header) + _chunk(b"IDAT", data) + _chunk(b"IEND", b"")


def _deflate(data: np.ndarray) -> bytes:
    if _isal is not None:
        return _isal.compress(data, 1)
    compressor = zlib.compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_HUFFMAN_ONLY)
    return compressor.compress(data) + compressor.flush()
