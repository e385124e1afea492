"""What a client asks of the labeling service: one frame in its wire formats and the options
that go with it. gRPC-free: the servicer builds a `FrameRequest` from a `LabelFrameRequest`
(serving.messages), the client builds one and sends it, `LabelingService` decodes it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from detmatch.structures import Calibration
from serving.decode import encode_points


@dataclass(frozen=True)
class RawImage:
    """Uncompressed 8-bit RGB pixels as sent: rgb holds height x width x 3 bytes, row-major."""

    width: int
    height: int
    rgb: bytes

    @classmethod
    def from_pixels(cls, pixels: np.ndarray) -> RawImage:
        """(H, W, 3) uint8 RGB -> its wire form."""
        pixels = np.asarray(pixels)
        if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[2] != 3:
            raise ValueError(f"raw image: expected (H, W, 3) uint8 RGB, got {pixels.dtype} "
                             f"{pixels.shape}")  # fmt: skip
        return cls(pixels.shape[1], pixels.shape[0], np.ascontiguousarray(pixels).tobytes())


@dataclass(frozen=True)
class LabelOptions:
    """Per-request overrides (None: the manifest's value) and whether to store the frame."""

    score_threshold_2d: float | None = None
    score_threshold_3d: float | None = None
    tau_hung: float | None = None
    store: bool = True


DEFAULT_OPTIONS = LabelOptions()  # the manifest's thresholds; store the frame


@dataclass(frozen=True)
class FrameRequest:
    """One frame to label, as sent: nothing is decoded or checked yet (`LabelingService`
    decodes it and names the field that is wrong, serving.decode).

    image: PNG or JPEG bytes, or raw_image: uncompressed pixels (exactly one of them).
    points: little-endian float32 bytes, N x 4 (x, y, z, intensity;
    LiDAR frame, metres). p2 (12 values), r0_rect (9), tr_velo_to_cam (12): KITTI's calibration
    matrices, row-major. namespace: the data set the frame id belongs to (None: the server's
    default)."""

    frame_id: str
    image: bytes
    points: bytes
    p2: Sequence[float]
    r0_rect: Sequence[float]
    tr_velo_to_cam: Sequence[float]
    namespace: str | None = None
    options: LabelOptions = DEFAULT_OPTIONS
    raw_image: RawImage | None = None

    @classmethod
    def from_arrays(
        cls,
        frame_id: str,
        image: bytes | np.ndarray,
        points: np.ndarray | bytes,
        calib: Calibration,
        *,
        namespace: str | None = None,
        options: LabelOptions = DEFAULT_OPTIONS,
    ) -> FrameRequest:
        """From what a KITTI reader gives: (N, 4) points (or their wire bytes), a Calibration;
        image: the PNG or JPEG file's bytes, or (H, W, 3) uint8 RGB pixels (sent raw)."""
        raw = None if isinstance(image, bytes) else RawImage.from_pixels(image)
        return cls(
            frame_id=frame_id,
            image=b"" if raw is not None else image,
            raw_image=raw,
            points=points if isinstance(points, bytes) else encode_points(points),
            p2=calib.P2.reshape(-1).tolist(),
            r0_rect=calib.R0_rect.reshape(-1).tolist(),
            tr_velo_to_cam=calib.Tr_velo_to_cam.reshape(-1).tolist(),
            namespace=namespace,
            options=options,
        )
