"""`LabelFrameRequest` <-> `FrameRequest`: the one conversion the client (sending) and the
servicer (receiving) share. Nothing is decoded or checked here; unset optional fields stay
None (the manifest's value), an unset `options.store` is True.
"""

from __future__ import annotations

from serving.proto import load as load_stubs
from serving.request import FrameRequest, LabelOptions, RawImage

pb2, _ = load_stubs()
OVERRIDES = ("score_threshold_2d", "score_threshold_3d", "tau_hung")


def request_message(request: FrameRequest) -> pb2.LabelFrameRequest:
    """The LabelFrameRequest a client sends for `request`."""
    options = pb2.LabelOptions(store=request.options.store)
    for name in OVERRIDES:
        value = getattr(request.options, name)
        if value is not None:
            setattr(options, name, value)
    message = pb2.LabelFrameRequest(
        frame_id=request.frame_id,
        image=request.image,
        points=request.points,
        calibration=pb2.Calibration(
            p2=request.p2, r0_rect=request.r0_rect, tr_velo_to_cam=request.tr_velo_to_cam
        ),
        options=options,
    )
    if request.namespace is not None:
        message.namespace = request.namespace
    if request.raw_image is not None:
        raw = request.raw_image
        message.raw_image.CopyFrom(pb2.RawImage(width=raw.width, height=raw.height, rgb=raw.rgb))
    return message


def frame_request(message: pb2.LabelFrameRequest) -> FrameRequest:
    """The FrameRequest a LabelFrameRequest carries. The calibration's repeated fields are
    passed on as they are, uncopied: decoding checks their lengths first, so a hostile
    million-value field is refused without being copied into a list."""
    options = message.options
    calibration = message.calibration
    return FrameRequest(
        frame_id=message.frame_id,
        image=message.image,
        points=message.points,
        p2=calibration.p2,
        r0_rect=calibration.r0_rect,
        tr_velo_to_cam=calibration.tr_velo_to_cam,
        namespace=message.namespace if message.HasField("namespace") else None,
        options=LabelOptions(
            **{name: _optional(options, name) for name in OVERRIDES},
            store=options.store if options.HasField("store") else True,
        ),
        raw_image=RawImage(message.raw_image.width, message.raw_image.height,
                           message.raw_image.rgb) if message.HasField("raw_image") else None,
    )  # fmt: skip


def _optional(message, name: str) -> float | None:
    return getattr(message, name) if message.HasField(name) else None
