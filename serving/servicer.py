"""The AutoLabeler servicer: protos in, `LabelingService` calls, protos out; nothing else.

A LabelFrame call runs in two halves on two thread pools, never on the event loop: the
request is converted and the frame decoded and labeled on the inference pool (CPU-bound,
`workers` threads), then stored on the I/O pool (file writes and fsyncs, which wait on the
disk). A call that does not store never waits for an I/O thread. Errors become status codes
in serving.errors alone.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import grpc

from serving.edge import call_fields
from serving.errors import status_for
from serving.messages import frame_request
from serving.metrics import ServiceMetrics
from serving.proto import load as load_stubs
from serving.serialize import BOX_2D_FIELDS, BOX_3D_FIELDS, label_records
from serving.service import LabeledFrame, LabelingService, LabelResult
from serving.store import StoreOutcome

pb2, pb2_grpc = load_stubs()
log = logging.getLogger("detmatch.serving")

SERVICE_NAME = pb2.DESCRIPTOR.services_by_name["AutoLabeler"].full_name
OUTCOMES = {
    StoreOutcome.CREATED: pb2.STORE_OUTCOME_CREATED,
    StoreOutcome.UNCHANGED: pb2.STORE_OUTCOME_UNCHANGED,
    StoreOutcome.REPLACED: pb2.STORE_OUTCOME_REPLACED,
}


class AutoLabelerServicer(pb2_grpc.AutoLabelerServicer):
    """Protos in and out; everything else is LabelingService's."""

    def __init__(
        self,
        service: LabelingService,
        metrics: ServiceMetrics,
        inference: ThreadPoolExecutor,
        storage: ThreadPoolExecutor,
    ) -> None:
        self.service = service
        self.metrics = metrics
        self.inference = inference
        self.storage = storage

    async def LabelFrame(self, request, context):  # noqa: N802 - gRPC's method name
        fields = call_fields()
        fields["frame_id"] = request.frame_id[:64]
        if request.namespace:
            fields["namespace"] = request.namespace[:64]
        if context.time_remaining() is not None and context.time_remaining() <= 0:
            await context.abort(
                grpc.StatusCode.DEADLINE_EXCEEDED, "deadline exceeded before labeling started"
            )
        loop = asyncio.get_running_loop()
        received_at = time.perf_counter()
        labeled = await loop.run_in_executor(
            self.inference, _status_or, self._label, request, received_at
        )
        if isinstance(labeled, _Failure):
            await context.abort(labeled.code, labeled.message)
        if labeled.stores:
            result = await loop.run_in_executor(
                self.storage, _status_or, self.service.store_labels, labeled
            )
            if isinstance(result, _Failure):
                await context.abort(result.code, result.message)
        else:
            result = self.service.store_labels(labeled)  # touches no disk: times the call
        outcome = None if result.stored is None else result.stored.outcome.value
        labels = result.result
        self.metrics.observe_frame(result.timings, labels.model_version, len(labels), outcome)
        fields.update(labels=len(labels), store=outcome or "not stored")
        return _response(result)

    def _label(self, request, received_at: float) -> LabeledFrame:
        return self.service.label(frame_request(request), received_at)

    async def GetModelInfo(self, request, context):  # noqa: N802 - gRPC's method name
        try:
            info = self.service.model_info()
        except Exception as error:  # noqa: BLE001 - status_for decides
            code, message = status_for(error)
            await context.abort(code, message)
        return pb2.ModelInfo(
            version=info["version"],
            classes=info["classes"],
            score_threshold_2d=info["score_threshold_2d"],
            score_threshold_3d=info["score_threshold_3d"],
            tau_hung=info["tau_hung"],
            tau_3d_outside_view=info["tau_3d_outside_view"],
            tau_3d_unmatched=info["tau_3d_unmatched"],
            metrics_json=json.dumps(info["metrics"]),
        )


@dataclass(frozen=True)
class _Failure:
    code: grpc.StatusCode
    message: str


def _status_or(function, *args):
    """function(*args), or the _Failure its exception maps to. Errors cross from the worker
    thread as values: an exception would carry its traceback, and with it the request and
    the frame's arrays, until the garbage collector breaks the cycle (measured: the RSS of a
    server answering bad calibrations grew by about 10 MB per call)."""
    try:
        return function(*args)
    except Exception as error:  # noqa: BLE001 - status_for decides
        code, message = status_for(error)
        if code == grpc.StatusCode.INTERNAL:
            log.exception("LabelFrame failed")
        return _Failure(code, message)


def _response(result: LabelResult) -> pb2.LabelFrameResponse:
    rows = []
    for record in label_records(result.result):
        row = pb2.Label(
            class_name=record.class_3d,
            box_3d=pb2.Box3D(**dict(zip(BOX_3D_FIELDS, record.box_3d, strict=True))),
            score_3d=record.score_3d,
            provenance=int(record.provenance),
        )
        if record.box_2d is not None:
            row.class_name_2d = record.class_2d
            row.box_2d.CopyFrom(pb2.Box2D(**dict(zip(BOX_2D_FIELDS, record.box_2d, strict=True))))
            row.score_2d = record.score_2d
            row.match_cost = record.cost
        rows.append(row)
    t = result.timings
    stored = result.stored
    return pb2.LabelFrameResponse(
        frame_id=result.frame_id,
        namespace=result.namespace,
        model_version=result.result.model_version,
        labels=rows,
        stored=stored is not None,
        store_outcome=pb2.STORE_OUTCOME_NOT_STORED if stored is None else OUTCOMES[stored.outcome],
        previous_model_version=(stored and stored.previous_version) or "",
        timing=pb2.Timing(
            total_s=t.get("total", 0.0),
            decode_s=t.get("decode", 0.0),
            detector2d_s=t.get("detector2d", 0.0),
            pillarize_s=t.get("pillarize", 0.0),
            detector3d_s=t.get("detector3d", 0.0),
            matching_s=t.get("matching", 0.0),
            store_s=t.get("store", 0.0),
        ),
    )
