"""Giving freed memory back to the operating system.

Frames are a few MB each (a PNG, a point cloud, their decoded arrays), allocated and freed by
many threads. glibc's malloc keeps what they free in per-thread arenas, and a stream of
requests that fail half way (a full frame with a bad calibration) fragments them: the
server's RSS grew by about 10 MB per such request, all of it free memory (measured in
BENCHMARKS.md). `malloc_trim(0)` every few seconds hands it back (about 30 ms for 300 MB).
A no-op where the C library has no malloc_trim (musl, macOS).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging

log = logging.getLogger("detmatch.serving")


@functools.cache
def _libc():
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    return libc if libc is not None and hasattr(libc, "malloc_trim") else None


def trim() -> bool:
    """Return the heap's free memory to the system; True if anything was released."""
    libc = _libc()
    return bool(libc.malloc_trim(0)) if libc is not None else False
