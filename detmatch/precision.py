"""Mixed precision for training: the detectors' forward passes under bfloat16 autocast.

`[train] precision`: "fp32", "bf16", or "auto" (bf16 where the hardware computes it natively:
a CPU with AVX-512 BF16 or AMX, or a CUDA GPU with bf16 support; else fp32). Only the forward
passes of students and teachers run under autocast; their outputs are cast back to fp32, so
losses, decoding, matching, the consistency loss, optimiser steps and the EMA stay fp32.
Evaluation and export run in fp32, as the deployed ONNX models do.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from detmatch.config import PRECISIONS


def bf16_native(device: torch.device) -> bool:
    """Whether the device computes bfloat16 matrix products natively."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    cpu = getattr(torch, "cpu", None)
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return torch.backends.mkldnn.is_available() and any(
        bool(getattr(cpu, name, lambda: False)()) for name in checks
    )


def autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of a precision setting on a device; None means fp32 throughout."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision == "bf16" or (precision == "auto" and bf16_native(device)):
        return torch.bfloat16
    return None


def autocast(device: torch.device, dtype: torch.dtype | None) -> torch.autocast:
    """A context in which forward passes run in dtype (a no-op for None)."""
    return torch.autocast(device.type, dtype=dtype or torch.bfloat16, enabled=dtype is not None)


def fp32(outputs: Sequence[torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """Raw outputs cast back to fp32 for losses and decoding."""
    return tuple(o.float() for o in outputs)
