"""The labeling service's domain object, testable without gRPC.

`LabelingService.label_frame` decodes a wire-format frame (serving.decode), labels it with the
currently served model and stores it; `ModelSlot` holds that model and swaps it atomically. A
request takes the slot's labeler once, at its start, so a swap never changes the model under a
request in flight, and every answer names the version that produced it.
"""

from __future__ import annotations

import io
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from detmatch.structures import Calibration
from serving.decode import (
    DEFAULT_MAX_IMAGE_PIXELS,
    decode_calibration,
    decode_frame_id,
    decode_image,
    decode_namespace,
    decode_points,
)
from serving.errors import InvalidInput, ModelUnavailable, StoreError
from serving.labeler import FrameLabels, Labeler
from serving.store import LabelStore, PutResult

log = logging.getLogger("detmatch.serving")


class ModelSlot:
    """The served labeler. `labeler` is read without a lock (one reference assignment)."""

    def __init__(self) -> None:
        self._labeler: Labeler | None = None
        self._swap_lock = threading.Lock()
        self.listeners: list[Any] = []

    @property
    def labeler(self) -> Labeler:
        labeler = self._labeler
        if labeler is None:
            raise ModelUnavailable("no model is loaded and warmed up yet")
        return labeler

    @property
    def version(self) -> str | None:
        labeler = self._labeler
        return None if labeler is None else labeler.version

    def swap(self, labeler: Labeler) -> Labeler | None:
        """Serve a loaded, warmed-up labeler; returns the one it replaces."""
        with self._swap_lock:
            old, self._labeler = self._labeler, labeler
        for listener in self.listeners:
            listener(labeler)
        return old


@dataclass(frozen=True)
class LabelOptions:
    """Per-request overrides (None: the manifest's value) and whether to store the frame."""

    score_threshold_2d: float | None = None
    score_threshold_3d: float | None = None
    tau_hung: float | None = None
    store: bool = True


@dataclass(frozen=True)
class DecodedFrame:
    """A request's fields, decoded and checked. image, points_bytes: the bytes as sent (PNG or
    JPEG; little-endian float32 N x 4, what the store writes without another copy)."""

    namespace: str
    frame_id: str
    pixels: np.ndarray
    kind: str
    image: bytes
    points: np.ndarray
    calib: Calibration
    points_bytes: bytes = b""

    def png(self) -> bytes:
        """The image as PNG bytes (what the store keeps): as sent, or re-encoded losslessly."""
        return self.image if self.kind == "png" else _png(self.pixels)


@dataclass(frozen=True)
class LabelResult:
    """stored: what the store did (None: not stored); timings: seconds per stage."""

    namespace: str
    frame_id: str
    result: FrameLabels
    stored: PutResult | None
    timings: dict[str, float] = field(default_factory=dict)


class LabelingService:
    """Decode, label, store: each step callable on its own (the gRPC server runs decoding and
    labeling on its inference threads and storing on its I/O threads), or all three at once
    with `label_frame`."""

    def __init__(
        self,
        slot: ModelSlot,
        store: LabelStore | None,
        max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS,
    ) -> None:
        self.slot = slot
        self.store = store
        self.max_image_pixels = max_image_pixels

    def decode(
        self,
        frame_id: str,
        image: bytes,
        points: bytes,
        p2: Sequence[float],
        r0_rect: Sequence[float],
        tr_velo_to_cam: Sequence[float],
        namespace: str | None = None,
    ) -> DecodedFrame:
        """InvalidInput naming the field for anything malformed."""
        namespace = decode_namespace(namespace)
        frame_id = decode_frame_id(frame_id)
        pixels, kind = decode_image(image, self.max_image_pixels)
        cloud = decode_points(points)
        calib = decode_calibration(p2, r0_rect, tr_velo_to_cam)
        return DecodedFrame(namespace, frame_id, pixels, kind, image, cloud, calib, points)

    def label(self, frame: DecodedFrame, options: LabelOptions = LabelOptions()) -> FrameLabels:
        """Label with the served model, taken once (a swap never changes it mid-request).
        ModelUnavailable without a model; InvalidInput for bad options."""
        labeler = self.slot.labeler
        try:
            return labeler.label(
                frame.pixels,
                frame.points,
                frame.calib,
                tau_hung=options.tau_hung,
                score_threshold_2d=options.score_threshold_2d,
                score_threshold_3d=options.score_threshold_3d,
            )
        except ValueError as error:
            raise InvalidInput(f"options.{error}") from None

    def store_labels(self, frame: DecodedFrame, result: FrameLabels) -> PutResult:
        if self.store is None:
            raise StoreError("this server has no label store")
        points = frame.points_bytes or frame.points
        return self.store.put(
            frame.frame_id, frame.png(), points, frame.calib, result, frame.namespace
        )

    def label_frame(
        self,
        frame_id: str,
        image: bytes,
        points: bytes,
        p2: Sequence[float],
        r0_rect: Sequence[float],
        tr_velo_to_cam: Sequence[float],
        options: LabelOptions = LabelOptions(),
        namespace: str | None = None,
    ) -> LabelResult:
        """Decode, label and (unless options.store is False or there is no store) store one
        frame. Raises InvalidInput for bad input, ModelUnavailable without a model."""
        start = time.perf_counter()
        frame = self.decode(frame_id, image, points, p2, r0_rect, tr_velo_to_cam, namespace)
        decoded = time.perf_counter()
        result = self.label(frame, options)
        labeled = time.perf_counter()
        stored = None
        if options.store and self.store is not None:
            stored = self.store_labels(frame, result)
        end = time.perf_counter()
        timings = {
            **result.timings,
            "decode": decoded - start,
            "store": end - labeled,
            "total": end - start,
        }
        return LabelResult(frame.namespace, frame.frame_id, result, stored, timings)

    def model_info(self) -> dict[str, Any]:
        labeler = self.slot.labeler
        return {
            "version": labeler.version,
            "classes": list(labeler.classes),
            "score_threshold_2d": labeler.score_threshold_2d,
            "score_threshold_3d": labeler.score_threshold_3d,
            "tau_hung": labeler.tau_hung,
            "tau_3d_outside_view": labeler.tau_3d_outside_view,
            "tau_3d_unmatched": labeler.tau_3d_unmatched,
            "metrics": labeler.manifest.training.metrics,
        }


def _png(pixels: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(pixels, mode="RGB").save(buffer, format="PNG", compress_level=6)
    return buffer.getvalue()
