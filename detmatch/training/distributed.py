"""torchrun / DistributedDataParallel set-up: gloo on CPU, NCCL on GPU, rank-0-only side effects.

Launch with `torchrun --nproc_per_node N -m detmatch.cli train ...` (one machine) or add
torchrun's --nnodes / --node_rank / --rdzv_endpoint flags for several machines.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist

from detmatch.config import DEVICES


@dataclass(frozen=True)
class DistributedContext:
    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1


def init_distributed(device_kind: str = "auto") -> DistributedContext:
    """Join the process group torchrun describes in the environment; a plain process is rank 0
    of 1 and needs no group. device_kind: "cuda" (GPU local_rank), "cpu", or "auto" (CUDA when
    there is a GPU)."""
    if device_kind not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(DEVICES)}, not {device_kind!r}")
    if device_kind == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: this torch build sees no CUDA GPU")
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device_kind != "cpu" and torch.cuda.is_available():
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
    else:
        device = torch.device("cpu")
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return DistributedContext(rank, world_size, local_rank, device)


def broadcast_buffers(module: torch.nn.Module, context: DistributedContext) -> None:
    """Give every rank rank 0's buffers (BatchNorm statistics). DDP broadcasts them at the start
    of each forward, so after the last step each rank still holds its own last update."""
    if context.enabled:
        for buffer in module.buffers():
            dist.broadcast(buffer, src=0)


def shutdown_distributed() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def barrier(context: DistributedContext) -> None:
    if context.enabled:
        dist.barrier()


class StepSampler(torch.utils.data.Sampler[tuple[int, int]]):
    """Indices for global steps start_step, start_step + 1, ...: each epoch is a permutation
    seeded by (seed, epoch); a step takes batch_size * world_size consecutive indices and this
    rank takes its slice. Resuming at a step replays exactly the data (and augmentation) an
    uninterrupted run would have seen."""

    def __init__(
        self,
        size: int,
        batch_size: int,
        seed: int,
        start_step: int,
        rank: int = 0,
        world_size: int = 1,
    ) -> None:
        self.size = size
        self.batch_size = batch_size
        self.seed = seed
        self.start_step = start_step
        self.rank = rank
        self.world_size = world_size

    def _stream(self, start: int, count: int) -> np.ndarray:
        """Positions [start, start + count) of the endless concatenation of seeded epochs."""
        taken: list[np.ndarray] = []
        while count > 0:
            epoch, offset = divmod(start, self.size)
            order = np.random.default_rng([self.seed, epoch]).permutation(self.size)
            part = order[offset : offset + count]
            taken.append(part)
            start, count = start + len(part), count - len(part)
        return np.concatenate(taken)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        """Yields (frame index, stream position); the position seeds the frame's augmentation."""
        per_step = self.batch_size * self.world_size
        step = self.start_step
        while True:
            indices = self._stream(step * per_step, per_step)
            first = self.rank * self.batch_size
            for slot in range(first, first + self.batch_size):
                yield int(indices[slot]), step * per_step + slot
            step += 1

    def epoch_of_step(self, step: int) -> int:
        return (step * self.batch_size * self.world_size) // self.size
