"""torchrun / DistributedDataParallel set-up: gloo on CPU, NCCL on GPU, rank-0-only side effects.

Launch with `torchrun --nproc_per_node N -m commands.main train ...` (one machine) or add
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
    """Leave the process group together: a barrier first, so that no rank tears down its
    connections while another still finishes (a gloo rank can then abort at exit with
    "terminate called without an active exception")."""
    if dist.is_initialized():
        try:
            dist.barrier()
        finally:
            dist.destroy_process_group()


def barrier(context: DistributedContext) -> None:
    if context.enabled:
        dist.barrier()


class StepSampler(torch.utils.data.Sampler[tuple[int, int]]):
    """Indices for global steps start_step, start_step + 1, ...: each epoch is a permutation
    seeded by (seed, epoch); a step takes batch_size * world_size consecutive indices and this
    rank takes its slice. Resuming at a step replays exactly the data (and augmentation) an
    uninterrupted run would have seen.

    repeat_factors (one per frame, >= 1), if given: each epoch holds frame i floor(r_i) times
    plus once more with probability frac(r_i) (detectron2's RepeatFactorTrainingSampler),
    drawn from the epoch's seed, so frames of rare classes come round more often.
    """

    def __init__(
        self,
        size: int,
        batch_size: int,
        seed: int,
        start_step: int,
        rank: int = 0,
        world_size: int = 1,
        repeat_factors: np.ndarray | None = None,
    ) -> None:
        self.size = size
        self.batch_size = batch_size
        self.seed = seed
        self.start_step = start_step
        self.rank = rank
        self.world_size = world_size
        self.repeat_factors = repeat_factors
        self._epoch_starts = [0]

    def epoch(self, epoch: int) -> np.ndarray:
        """The frame indices of one epoch, in order."""
        rng = np.random.default_rng([self.seed, epoch])
        if self.repeat_factors is None:
            return rng.permutation(self.size)
        whole = np.floor(self.repeat_factors).astype(np.int64)
        extra = rng.random(self.size) < self.repeat_factors - whole
        repeated = np.repeat(np.arange(self.size), whole + extra)
        return repeated[rng.permutation(len(repeated))]

    def _locate(self, position: int) -> tuple[int, int]:
        """(epoch, offset in it) of a stream position."""
        if self.repeat_factors is None:
            return divmod(position, self.size)
        while self._epoch_starts[-1] <= position:
            epoch = len(self._epoch_starts) - 1
            self._epoch_starts.append(self._epoch_starts[-1] + len(self.epoch(epoch)))
        epoch = int(np.searchsorted(self._epoch_starts, position, side="right")) - 1
        return epoch, position - self._epoch_starts[epoch]

    def _stream(self, start: int, count: int) -> np.ndarray:
        """Positions [start, start + count) of the endless concatenation of seeded epochs."""
        taken: list[np.ndarray] = []
        while count > 0:
            epoch, offset = self._locate(start)
            part = self.epoch(epoch)[offset : offset + count]
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


def repeat_factors(presence: np.ndarray, threshold: float) -> np.ndarray:
    """Per-frame repeat factors from a (frames, classes) presence matrix: class c's factor is
    max(1, sqrt(threshold / f_c)) with f_c the fraction of frames holding c; a frame takes its
    classes' largest (1 for a frame with none)."""
    fractions = presence.mean(axis=0)
    per_class = np.maximum(1.0, np.sqrt(threshold / np.maximum(fractions, 1e-12)))
    factors = np.where(presence, per_class[None, :], 1.0)
    return factors.max(axis=1) if factors.shape[1] else np.ones(len(presence))
