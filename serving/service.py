"""The labeling service's domain object, testable without gRPC.

`LabelingService.label_frame` decodes a `FrameRequest` (serving.decode), labels it with the
currently served model and stores it; `ModelSlot` holds that model and swaps it atomically. A
request takes the slot's labeler once, at its start, so a swap never changes the model under a
request in flight, and every answer names the version that produced it.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from detmatch.structures import Calibration
from serving.batching import Batcher
from serving.decode import (
    DEFAULT_MAX_IMAGE_PIXELS,
    DEFAULT_MAX_POINTS,
    decode_calibration,
    decode_frame_id,
    decode_image,
    decode_namespace,
    decode_points,
    decode_raw_image,
)
from serving.errors import InvalidInput, ModelUnavailable
from serving.labeler import Frame, FrameLabels, Labeler, Overrides
from serving.png import encode_png
from serving.request import FrameRequest
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
class DecodedFrame:
    """A request's fields, decoded and checked. image, points_bytes: the bytes as sent (PNG or
    JPEG, empty for raw pixels; little-endian float32 N x 4, what the store writes without
    another copy)."""

    namespace: str
    frame_id: str
    pixels: np.ndarray
    kind: str
    image: bytes
    points: np.ndarray
    calib: Calibration
    points_bytes: bytes

    def png(self) -> bytes:
        """The image as PNG bytes (what the store keeps): as sent, or re-encoded losslessly."""
        return self.image if self.kind == "png" else encode_png(self.pixels)


@dataclass(frozen=True)
class LabeledFrame:
    """A request's first half done: its frame decoded and labeled. stores: whether
    `store_labels` will write it; received_at, labeled_at: time.perf_counter() readings;
    decode_s: seconds spent decoding."""

    frame: DecodedFrame
    labels: FrameLabels
    stores: bool
    received_at: float
    decode_s: float
    labeled_at: float


@dataclass(frozen=True)
class LabelResult:
    """stored: what the store did (None: not stored); timings: seconds per stage."""

    namespace: str
    frame_id: str
    result: FrameLabels
    stored: PutResult | None
    timings: dict[str, float] = field(default_factory=dict)


class LabelingService:
    """Decode, label, store. A request runs in two halves, one per kind of work, so a server
    can give each its own threads: `label` (decode and label: CPU) and `store_labels` (file
    writes and fsyncs: the disk); `label_frame` runs both in turn."""

    def __init__(
        self,
        slot: ModelSlot,
        store: LabelStore | None,
        max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS,
        max_points: int = DEFAULT_MAX_POINTS,
        batcher: Batcher | None = None,
    ) -> None:
        """batcher: label concurrent calls' frames in batches (serving.batching); None: each
        call labels its own frame."""
        self.slot = slot
        self.store = store
        self.max_image_pixels = max_image_pixels
        self.max_points = max_points
        self.batcher = batcher

    def label_frame(self, request: FrameRequest) -> LabelResult:
        """Decode, label and (unless options.store is False or there is no store) store one
        frame. Raises InvalidInput for bad input, ModelUnavailable without a model."""
        return self.store_labels(self.label(request))

    def label(self, request: FrameRequest, received_at: float | None = None) -> LabeledFrame:
        """Decode and label with the served model, taken once (a swap never changes it
        mid-request). received_at: when the request arrived (time.perf_counter(); None: now),
        the start of its total time. InvalidInput for a malformed field or option,
        ModelUnavailable without a model."""
        start = time.perf_counter()
        frame = self.decode(request)
        decoded = time.perf_counter()
        labeler = self.slot.labeler
        options = request.options
        overrides = Overrides(
            tau_hung=options.tau_hung,
            score_threshold_2d=options.score_threshold_2d,
            score_threshold_3d=options.score_threshold_3d,
        )
        try:
            if self.batcher is None:
                labels = labeler.label(frame.pixels, frame.points, frame.calib,
                                       **dataclasses.asdict(overrides))  # fmt: skip
            else:
                item = Frame(frame.pixels, frame.points, frame.calib, overrides)
                labels = self.batcher.label(labeler, item)
        except ValueError as error:
            raise InvalidInput(f"options.{error}") from None
        return LabeledFrame(
            frame=frame,
            labels=labels,
            stores=options.store and self.store is not None,
            received_at=start if received_at is None else received_at,
            decode_s=decoded - start,
            labeled_at=time.perf_counter(),
        )

    def decode(self, request: FrameRequest) -> DecodedFrame:
        """InvalidInput naming the field for anything malformed."""
        namespace = decode_namespace(request.namespace)
        frame_id = decode_frame_id(request.frame_id)
        raw = request.raw_image
        if raw is not None and request.image:
            raise InvalidInput("image: set image (PNG or JPEG) or raw_image, not both")
        if raw is not None:
            pixels = decode_raw_image(raw.width, raw.height, raw.rgb, self.max_image_pixels)
            kind = "raw"
        else:
            pixels, kind = decode_image(request.image, self.max_image_pixels)
        cloud = decode_points(request.points, self.max_points)
        calib = decode_calibration(request.p2, request.r0_rect, request.tr_velo_to_cam)
        return DecodedFrame(
            namespace, frame_id, pixels, kind, request.image, cloud, calib, request.points
        )

    def store_labels(self, labeled: LabeledFrame) -> LabelResult:
        """Store the frame if its request asked to (`labeled.stores`: without it nothing here
        touches the disk) and time the request. StoreError when the store cannot record it."""
        frame, labels = labeled.frame, labeled.labels
        stored = None
        if labeled.stores:
            stored = self.store.put(
                frame.frame_id, frame.png(), frame.points_bytes, frame.calib, labels,
                frame.namespace,
            )  # fmt: skip
        end = time.perf_counter()
        timings = {
            **labels.timings,
            "decode": labeled.decode_s,
            "store": end - labeled.labeled_at,
            "total": end - labeled.received_at,
        }
        return LabelResult(frame.namespace, frame.frame_id, labels, stored, timings)

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
