"""Supervised training of both detectors (the labeled-only stage of DetMatch).

One step trains the 2D and the 3D detector on the same labeled frames, each with its own
optimiser (docs/design.md section 3). Rank 0 alone logs, evaluates and writes checkpoints.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from detmatch.checkpoints import (
    checkpoint_path,
    list_checkpoints,
    load_checkpoint,
    resolve_checkpoint,
)
from detmatch.config import ExperimentConfig, TrainConfig, config_to_dict
from detmatch.data.dataset import Batch, FrameDataset, Sample, collate
from detmatch.models.build import build_detectors
from detmatch.models.contract import Detector2D, Detector3D, forward_pillars
from detmatch.models.pillars import PillarGrid, Pillars
from detmatch.precision import autocast, autocast_dtype, fp32
from detmatch.training.checkpoint import restore_rng_state, rng_state, save_checkpoint
from detmatch.training.distributed import (
    DistributedContext,
    StepSampler,
    barrier,
    broadcast_buffers,
    repeat_factors,
)
from detmatch.training.evaluation import evaluate_detectors

CHECKPOINT_FORMAT = 1


def build_optimizers(
    config: ExperimentConfig, model_2d: torch.nn.Module, model_3d: torch.nn.Module
) -> tuple[torch.optim.Optimizer, torch.optim.Optimizer]:
    """SGD (momentum 0.9, weight decay 1e-4) for 2D; AdamW (0.95, 0.99; 0.01) for 3D."""
    train = config.train
    sgd = torch.optim.SGD(
        model_2d.parameters(),
        lr=train.lr_2d,
        momentum=train.momentum_2d,
        weight_decay=train.weight_decay_2d,
    )
    adamw = torch.optim.AdamW(
        model_3d.parameters(),
        lr=train.lr_3d,
        betas=train.betas_3d,
        weight_decay=train.weight_decay_3d,
    )
    return sgd, adamw


def warmup_factor(step: int, warmup_steps: int) -> float:
    """Linear warm-up to 1 over warmup_steps, then constant."""
    return min(1.0, (step + 1) / max(warmup_steps, 1))


def step_factor(step: int, steps: int, milestones: tuple[float, ...]) -> float:
    """x0.1 for each milestone (a fraction of steps) passed."""
    return 0.1 ** sum(step >= m * steps for m in milestones)


def onecycle_factor(step: int, steps: int, peak: float, div: float) -> float:
    """OpenPCDet's one-cycle: cosine from 1/div up to 1 at peak * steps, then cosine down to
    1 / div / 1e4 at the end."""
    fraction = step / max(steps, 1)

    def cosine(start: float, end: float, t: float) -> float:
        return end + (start - end) / 2 * (1 + math.cos(math.pi * min(max(t, 0.0), 1.0)))

    if fraction < peak:
        return cosine(1 / div, 1.0, fraction / peak)
    return cosine(1.0, 1 / div / 1e4, (fraction - peak) / max(1 - peak, 1e-12))


def learning_rates(train: TrainConfig, step: int) -> tuple[float, float]:
    """(2D, 3D) learning rates at a step: the schedules of [train], the 2D one and a constant
    3D one after the linear warm-up (one-cycle has its own ramp)."""
    warmup = warmup_factor(step, train.warmup_steps)
    lr_2d = train.lr_2d * warmup
    if train.schedule_2d == "step":
        lr_2d *= step_factor(step, train.steps, train.milestones_2d)
    if train.schedule_3d == "onecycle":
        lr_3d = train.lr_3d * onecycle_factor(
            step, train.steps, train.onecycle_peak, train.onecycle_div
        )
    else:
        lr_3d = train.lr_3d * warmup
    return lr_2d, lr_3d


@dataclass
class TrainState:
    """Everything a run needs to continue. model_* are the trained (student) models; teacher_*
    exist in teacher-student runs and are then the run's output."""

    model_2d: Detector2D
    model_3d: Detector3D
    optimizer_2d: torch.optim.Optimizer
    optimizer_3d: torch.optim.Optimizer
    step: int = 0
    metrics: dict[str, Any] = field(default_factory=dict)
    teacher_2d: Detector2D | None = None
    teacher_3d: Detector3D | None = None

    @property
    def output_models(self) -> tuple[Detector2D, Detector3D]:
        """The models a run delivers: the teachers if there are any, else the trained models."""
        if self.teacher_2d is not None and self.teacher_3d is not None:
            return self.teacher_2d, self.teacher_3d
        return self.model_2d, self.model_3d

    def to_checkpoint(self, config: ExperimentConfig) -> dict[str, Any]:
        """model_2d / model_3d always hold the output models, so prediction and export read any
        checkpoint the same way; students are stored beside teachers."""
        output_2d, output_3d = self.output_models
        checkpoint = {
            "format": CHECKPOINT_FORMAT,
            "step": self.step,
            "config": config_to_dict(config),
            "classes": list(config.data.classes),
            "model_2d": output_2d.state_dict(),
            "model_3d": output_3d.state_dict(),
            "optimizer_2d": self.optimizer_2d.state_dict(),
            "optimizer_3d": self.optimizer_3d.state_dict(),
            "rng": rng_state(),
            "metrics": self.metrics,
        }
        if self.teacher_2d is not None:
            checkpoint["student_2d"] = self.model_2d.state_dict()
            checkpoint["student_3d"] = self.model_3d.state_dict()
        return checkpoint

    def load(self, checkpoint: dict[str, Any]) -> None:
        if checkpoint.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"unsupported checkpoint format {checkpoint.get('format')!r}")
        if self.teacher_2d is not None:
            if "student_2d" not in checkpoint:
                raise ValueError("a teacher-student run cannot resume from a supervised checkpoint")
            self.teacher_2d.load_state_dict(checkpoint["model_2d"])
            self.teacher_3d.load_state_dict(checkpoint["model_3d"])
            self.model_2d.load_state_dict(checkpoint["student_2d"])
            self.model_3d.load_state_dict(checkpoint["student_3d"])
        else:
            self.model_2d.load_state_dict(checkpoint["model_2d"])
            self.model_3d.load_state_dict(checkpoint["model_3d"])
        self.optimizer_2d.load_state_dict(checkpoint["optimizer_2d"])
        self.optimizer_3d.load_state_dict(checkpoint["optimizer_3d"])
        self.step = int(checkpoint["step"])
        self.metrics = dict(checkpoint.get("metrics", {}))
        restore_rng_state(checkpoint["rng"])


def clip_and_step(
    optimizer: torch.optim.Optimizer, model: torch.nn.Module, clip: float, lr: float
) -> float:
    for group in optimizer.param_groups:
        group["lr"] = lr
    norm = torch.nn.utils.clip_grad_norm_(model.parameters(), clip)
    optimizer.step()
    return float(norm)


def ground_truth_targets(
    model_2d: Detector2D, model_3d: Detector3D, samples: list[Sample]
) -> tuple[list[Any], list[Any]]:
    """Per-sample 2D and 3D training targets from the samples' labels (3D background learned
    only inside the camera's view)."""
    targets_2d = [model_2d.build_targets(s.gt_2d, s.image_transform.input_size) for s in samples]
    targets_3d = [model_3d.build_targets(s.gt_3d, s.camera_view) for s in samples]
    return targets_2d, targets_3d


def labeled_training_frames(
    config: ExperimentConfig, grid: PillarGrid, progress: bool = False
) -> FrameDataset:
    """The labeled training stream: the train split with flip and the config's [augment]
    (ground-truth sampling from its own frames, rotation and scale, the 2D multi-scale window),
    2D training boxes as [data] train_boxes_2d says."""
    data, train = config.data, config.train
    return FrameDataset(
        data.root, data.train_split, data.classes, data.image_size, grid,
        augment=True, flip_probability=train.flip_probability, seed=train.seed,
        projected_2d=data.train_boxes_2d == "projected", labeled_augment=config.augment,
        progress=progress,
    )  # fmt: skip


def load_2d_start(model_2d: Detector2D, config: ExperimentConfig) -> None:
    """Load [train] init_2d's 2D detector into model_2d; a ValueError naming the checkpoint
    when its classes or [detector2d] differ from the config's."""
    path = resolve_checkpoint(Path(config.train.init_2d))
    checkpoint = load_checkpoint(path)
    stored = checkpoint["config"]
    if list(checkpoint["classes"]) != list(config.data.classes):
        raise ValueError(
            f"[train] init_2d {path}: classes {checkpoint['classes']} differ from "
            f"{list(config.data.classes)}"
        )
    wanted = config_to_dict(config)["detector2d"]
    if stored["detector2d"] != wanted:
        raise ValueError(f"[train] init_2d {path}: its [detector2d] differs from this config's")
    model_2d.load_state_dict(checkpoint["model_2d"])


def leave_cores_for_workers(data_workers: int, context: DistributedContext) -> int:
    """On CPU, the number of torch threads this process keeps so that its data workers get a
    core each: the worker's loading and the step's OpenMP threads no longer fight over cores
    (on 2 cores with one worker: 0.63 -> 0.44 s a pre-training step, BENCHMARKS.md). Left
    alone (returns the current count) on CUDA, without workers, or when OMP_NUM_THREADS is
    set."""
    if context.device.type != "cpu" or data_workers == 0 or "OMP_NUM_THREADS" in os.environ:
        return torch.get_num_threads()
    cores = len(os.sched_getaffinity(0)) // max(context.world_size, 1)
    threads = max(1, cores - data_workers)
    torch.set_num_threads(threads)
    return threads


class SupervisedTrainer:
    """Labeled-only training of both detectors with periodic evaluation and checkpoints."""

    def __init__(
        self, config: ExperimentConfig, run_dir: Path, context: DistributedContext
    ) -> None:
        self.config = config
        self.run_dir = Path(run_dir)
        self.context = context
        torch.manual_seed(config.train.seed)
        self.device = context.device
        self.autocast_dtype = autocast_dtype(config.train.precision, self.device)
        model_2d, model_3d = (model.to(self.device) for model in build_detectors(config))
        if config.train.init_2d:
            load_2d_start(model_2d, config)
        # The 2D detector's convolutions run ~1.3x faster on channels-last tensors (oneDNN).
        model_2d.to(memory_format=torch.channels_last)
        optimizer_2d, optimizer_3d = build_optimizers(config, model_2d, model_3d)
        self.state = TrainState(model_2d, model_3d, optimizer_2d, optimizer_3d)
        self.forward_2d: torch.nn.Module = model_2d
        self.forward_3d: torch.nn.Module = model_3d
        if context.enabled:
            devices = [self.device] if self.device.type == "cuda" else None
            self.forward_2d = DistributedDataParallel(model_2d, device_ids=devices)
            self.forward_3d = DistributedDataParallel(model_3d, device_ids=devices)
        grid = model_3d.grid
        data = config.data
        self.train_set = labeled_training_frames(config, grid, progress=context.is_main)
        self.val_set = FrameDataset(data.root, data.val_split, data.classes, data.image_size, grid)

    def resume(self) -> bool:
        """Load the run's latest checkpoint if there is one; True if resumed."""
        found = list_checkpoints(self.run_dir)
        if not found:
            return False
        self.state.load(load_checkpoint(found[-1]))
        return True

    def train_step(self, batch: Batch) -> dict[str, float]:
        state = self.state
        batch = batch.to(self.device)
        state.model_2d.train()
        state.model_3d.train()
        targets_2d, targets_3d = ground_truth_targets(state.model_2d, state.model_3d, batch.samples)
        losses_2d = state.model_2d.loss(self.run_2d(batch.images), targets_2d)
        losses_3d = state.model_3d.loss(self.run_3d(batch.pillars), targets_3d)
        loss_2d, loss_3d = sum(losses_2d.values()), sum(losses_3d.values())
        record = self.optimise(loss_2d + loss_3d)
        record.update({f"loss_2d/{k}": v.item() for k, v in losses_2d.items()})
        record.update({f"loss_3d/{k}": v.item() for k, v in losses_3d.items()})
        record.update(loss_2d=loss_2d.item(), loss_3d=loss_3d.item())
        return record

    def run_2d(self, images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The trained 2D detector's raw outputs (through DDP, in the configured precision),
        in fp32."""
        images = images.contiguous(memory_format=torch.channels_last)
        with autocast(self.device, self.autocast_dtype):
            return fp32(self.forward_2d(images))

    def run_3d(self, pillars: Pillars) -> tuple[torch.Tensor, ...]:
        """The trained 3D detector's raw outputs, like run_2d."""
        with autocast(self.device, self.autocast_dtype):
            return fp32(forward_pillars(self.forward_3d, pillars))

    def optimise(self, loss: torch.Tensor) -> dict[str, float]:
        """One optimiser step of both detectors on a loss (warm-up, clipping); the step count
        advances. Returns the gradient norms and learning rates."""
        state, train = self.state, self.config.train
        state.optimizer_2d.zero_grad(set_to_none=True)
        state.optimizer_3d.zero_grad(set_to_none=True)
        loss.backward()
        lr_2d, lr_3d = learning_rates(train, state.step)
        grad_2d = clip_and_step(state.optimizer_2d, state.model_2d, train.grad_clip, lr_2d)
        grad_3d = clip_and_step(state.optimizer_3d, state.model_3d, train.grad_clip, lr_3d)
        state.step += 1
        return {"grad_norm_2d": grad_2d, "grad_norm_3d": grad_3d, "lr_2d": lr_2d, "lr_3d": lr_3d}

    def loader(
        self,
        dataset: torch.utils.data.Dataset,
        collate_fn,
        seed: int,
        repeat: np.ndarray | None = None,
    ) -> torch.utils.data.DataLoader:
        """Endless batches from the current step on (StepSampler), this rank's share; repeat:
        per-frame repeat factors (None: each frame once an epoch)."""
        train = self.config.train
        sampler = StepSampler(
            size=len(dataset),
            batch_size=train.batch_size,
            seed=seed,
            start_step=self.state.step,
            rank=self.context.rank,
            world_size=self.context.world_size,
            repeat_factors=repeat,
        )
        return torch.utils.data.DataLoader(
            dataset,
            batch_size=train.batch_size,
            sampler=sampler,
            collate_fn=collate_fn,
            num_workers=self.config.data.num_workers,
            persistent_workers=self.config.data.num_workers > 0,
        )

    @property
    def data_workers(self) -> int:
        """Data-loading worker processes that batches() starts."""
        return self.config.data.num_workers

    def batches(self) -> Iterator[Any]:
        """What train_step consumes, one item a step."""
        threshold = self.config.augment.repeat_factor_threshold
        repeat = None
        if threshold > 0:
            repeat = repeat_factors(self.train_set.class_presence(), threshold)
        return iter(self.loader(self.train_set, collate, self.config.train.seed, repeat))

    def save(self) -> Path:
        path = checkpoint_path(self.run_dir, self.state.step)
        save_checkpoint(path, self.state.to_checkpoint(self.config))
        return path

    def evaluate(self) -> dict[str, Any]:
        """Score the run's output models on the val split."""
        model_2d, model_3d = self.state.output_models
        return evaluate_detectors(
            model_2d, model_3d, self.val_set, self.config.data.classes,
            batch_size=self.config.train.batch_size, num_workers=self.config.data.num_workers,
        )  # fmt: skip

    def run(self, stop_after: int | None = None) -> TrainState:
        """Train up to config.train.steps (or stop_after more steps, for tests that simulate a
        killed run), evaluating and checkpointing on the configured periods."""
        train, main = self.config.train, self.context.is_main
        last = train.steps if stop_after is None else min(train.steps, self.state.step + stop_after)
        if main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            (self.run_dir / "config.json").write_text(
                json.dumps(config_to_dict(self.config), indent=2)
            )
        log = (self.run_dir / "metrics.jsonl").open("a") if main else None
        progress = tqdm(
            total=last, initial=self.state.step, desc="train", disable=not main, dynamic_ncols=True
        )
        batches = self.batches()
        threads = torch.get_num_threads()
        leave_cores_for_workers(self.data_workers, self.context)
        started = time.monotonic()
        try:
            while self.state.step < last:
                record = self.train_step(next(batches))
                if self.state.step == last:
                    broadcast_buffers(self.state.model_2d, self.context)
                    broadcast_buffers(self.state.model_3d, self.context)
                step = self.state.step
                progress.update(1)
                if main and (step % train.log_every == 0 or step == last):
                    record.update(step=step, elapsed_s=round(time.monotonic() - started, 3))
                    log.write(json.dumps(record) + "\n")
                    log.flush()
                    progress.set_postfix(
                        loss_2d=f"{record['loss_2d']:.3f}", loss_3d=f"{record['loss_3d']:.3f}"
                    )
                if step % train.eval_every == 0 or step == train.steps:
                    if main:
                        self.state.metrics = self.evaluate()
                        log.write(json.dumps({"step": step, "eval": self.state.metrics}) + "\n")
                        log.flush()
                    barrier(self.context)
                if main and (step % train.checkpoint_every == 0 or step == last):
                    self.save()
        finally:
            torch.set_num_threads(threads)
            progress.close()
            if log is not None:
                log.close()
        return self.state
