"""Domain errors of the labeling service and the one place that maps them to gRPC codes.

The domain (decoding, the labeler, the store) raises plain Python errors; the servicer calls
`status_for` and nothing else decides a status code. Bad input is INVALID_ARGUMENT, over-size
input RESOURCE_EXHAUSTED, no loaded model UNAVAILABLE; only a genuine bug is INTERNAL.
"""

from __future__ import annotations

import grpc

from detmatch.data.kitti import KittiFormatError


class InvalidInput(ValueError):
    """A request field the service cannot use; the message names the field and the problem."""


class InputTooLarge(ValueError):
    """A request field beyond the service's limits."""


class ModelUnavailable(RuntimeError):
    """No model is loaded and warmed up yet (or the server is shutting down)."""


class StoreError(RuntimeError):
    """The label store could not record a frame (full disk, permissions...)."""


def status_for(error: BaseException) -> tuple[grpc.StatusCode, str]:
    """The status code and message a client gets for a domain error."""
    if isinstance(error, InputTooLarge):
        return grpc.StatusCode.RESOURCE_EXHAUSTED, str(error)
    if isinstance(error, (InvalidInput, KittiFormatError, ValueError)):
        return grpc.StatusCode.INVALID_ARGUMENT, str(error)
    if isinstance(error, ModelUnavailable):
        return grpc.StatusCode.UNAVAILABLE, str(error)
    if isinstance(error, StoreError):
        return grpc.StatusCode.UNAVAILABLE, f"label store: {error}"
    return grpc.StatusCode.INTERNAL, f"internal error: {type(error).__name__}"
