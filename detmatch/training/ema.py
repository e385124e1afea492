"""Exponential-moving-average teachers (docs/design.md section 3)."""

from __future__ import annotations

import torch


def ema_decay(iteration: int, offset: int = 100, max_decay: float = 0.999) -> float:
    """d = min(1 - 1 / (iteration + offset), max_decay): 0.99 at iteration 0, rising to 0.999."""
    return min(1.0 - 1.0 / (iteration + offset), max_decay)


@torch.no_grad()
def ema_update(teacher: torch.nn.Module, student: torch.nn.Module, decay: float) -> None:
    """theta_T <- d theta_T + (1 - d) theta_S for every parameter and floating-point buffer
    (BatchNorm statistics); integer buffers (batch counters) are copied."""
    student_state = student.state_dict()
    for name, value in teacher.state_dict().items():
        source = student_state[name]
        if value.dtype.is_floating_point:
            value.mul_(decay).add_(source.to(value.dtype), alpha=1.0 - decay)
        else:
            value.copy_(source)
