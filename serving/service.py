"""The labeling service's domain object, testable without gRPC.

`LabelingService.label_frame` decodes a wire-format frame (serving.decode), labels it with the
currently served model and stores it; `ModelSlot` holds that model and swaps it atomically. A
request takes the slot's labeler once, at its start, so a swap never changes the model under a
request in flight, and every answer names the version that produced it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from serving.decode import decode_calibration, decode_frame_id, decode_image, decode_points
from serving.errors import InvalidInput, ModelUnavailable
from serving.labeler import FrameLabels, Labeler
from serving.store import LabelStore, StoredFrame

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
class LabelResult:
    frame_id: str
    result: FrameLabels
    stored: StoredFrame | None
    newly_stored: bool
    timings: dict[str, float] = field(default_factory=dict)


class LabelingService:
    def __init__(self, slot: ModelSlot, store: LabelStore | None) -> None:
        self.slot = slot
        self.store = store

    def label_frame(
        self,
        frame_id: str,
        image: bytes,
        points: bytes,
        p2: Sequence[float],
        r0_rect: Sequence[float],
        tr_velo_to_cam: Sequence[float],
        options: LabelOptions = LabelOptions(),
    ) -> LabelResult:
        """Decode, label and (unless options.store is False) store one frame. Raises
        InvalidInput/InputTooLarge for bad input, ModelUnavailable without a model."""
        start = time.perf_counter()
        frame_id = decode_frame_id(frame_id)
        pixels, kind = decode_image(image)
        cloud = decode_points(points)
        calib = decode_calibration(p2, r0_rect, tr_velo_to_cam)
        decoded = time.perf_counter()
        labeler = self.slot.labeler  # fixed for the whole request
        try:
            result = labeler.label(
                pixels,
                cloud,
                calib,
                tau_hung=options.tau_hung,
                score_threshold_2d=options.score_threshold_2d,
                score_threshold_3d=options.score_threshold_3d,
            )
        except ValueError as error:
            raise InvalidInput(f"options.{error}") from None
        labeled = time.perf_counter()
        stored, newly = None, False
        if options.store and self.store is not None:
            png = image if kind == "png" else _png(pixels)
            stored, newly = self.store.put(frame_id, png, cloud, calib, result)
        end = time.perf_counter()
        timings = {
            **result.timings,
            "decode": decoded - start,
            "store": end - labeled,
            "total": end - start,
        }
        return LabelResult(frame_id, result, stored, newly, timings)

    def model_info(self) -> dict[str, Any]:
        labeler = self.slot.labeler
        return {
            "version": labeler.version,
            "classes": list(labeler.classes),
            "score_threshold_2d": labeler.score_threshold_2d,
            "score_threshold_3d": labeler.score_threshold_3d,
            "tau_hung": labeler.tau_hung,
            "tau_3d_outside_view": labeler.tau_3d_outside_view,
            "metrics": labeler.manifest.training.metrics,
        }


def _png(pixels) -> bytes:
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(pixels, mode="RGB").save(buffer, format="PNG", compress_level=6)
    return buffer.getvalue()
