"""Teacher-student training: confidence thresholding and DetMatch (docs/design.md section 3).

Each step takes equal numbers of labeled and unlabeled frames. `train_step` reads like the
method: teacher predictions on the weak views, pseudo-labels by the method's rule
(`detmatch.training.rules`) in the un-augmented frame, moved into the students' frames, student
losses (supervised + pseudo-label + consistency), optimiser steps, EMA update of the teachers.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from detmatch.checkpoints import load_checkpoint, resolve_checkpoint
from detmatch.config import ExperimentConfig
from detmatch.data.dataset import Batch, FrameDataset
from detmatch.data.unlabeled import UnlabeledBatch, UnlabeledDataset, collate_unlabeled
from detmatch.inference import predict_batch
from detmatch.models.contract import Detector2D, Detector3D, split_outputs
from detmatch.training.consistency import ConsistencyWeights, consistency_loss
from detmatch.training.distributed import DistributedContext
from detmatch.training.ema import ema_decay, ema_update
from detmatch.training.rules import FramePseudoLabels, pseudo_label_rule
from detmatch.training.trainer import SupervisedTrainer, ground_truth_targets


def _frozen_copy(model: torch.nn.Module) -> torch.nn.Module:
    teacher = copy.deepcopy(model).eval()
    for parameter in teacher.parameters():
        parameter.requires_grad_(False)
    return teacher


def load_pretrained(model: torch.nn.Module, state: dict[str, torch.Tensor]) -> list[str]:
    """Load pre-trained weights; a second stage the pre-training did not have (the 3D
    detector's `refinement.*`) may be missing and keeps its fresh weights, which return the
    first stage's boxes unchanged. Returns those missing keys; any other mismatch raises."""
    missing, unexpected = model.load_state_dict(state, strict=False)
    fresh = [k for k in missing if k.startswith("refinement.")]
    absent = sorted(set(missing) - set(fresh))
    if absent or unexpected:
        raise RuntimeError(
            f"pre-trained weights do not fit {type(model).__name__}: "
            f"missing {absent}, unexpected {sorted(unexpected)}"
        )
    return fresh


def _total(losses: dict[str, torch.Tensor]) -> torch.Tensor:
    return sum(losses.values())


def pseudo_label_targets(
    student_2d: Detector2D,
    student_3d: Detector3D,
    unlabeled: UnlabeledBatch,
    pseudo: list[FramePseudoLabels],
) -> tuple[list[Any], list[Any]]:
    """The students' targets from pseudo-labels moved into their frames (3D background is
    learned everywhere: the fallback labels cover what the camera cannot see; 2D background
    everywhere but the rule's ignore regions)."""
    labels_2d, labels_3d = unlabeled.to_student_frames(
        [p.labels_2d for p in pseudo], [p.labels_3d for p in pseudo]
    )
    samples = unlabeled.weak.samples
    targets_2d = [
        student_2d.build_targets(
            labels,
            sample.image_transform.input_size,
            p.ignore_2d.map_boxes(sample.image_transform.apply).boxes,
        )
        for labels, p, sample in zip(labels_2d, pseudo, samples, strict=True)
    ]
    targets_3d = [student_3d.build_targets(labels) for labels in labels_3d]
    return targets_2d, targets_3d


def step_record(
    loss: torch.Tensor,
    optimised: dict[str, float],
    losses: dict[str, dict[str, torch.Tensor]],
    consistency: torch.Tensor,
    pairs: int,
    pseudo: list[FramePseudoLabels],
) -> dict[str, float]:
    """What a teacher-student step writes to metrics.jsonl: the total loss, the optimiser's
    figures (gradient norms, learning rates, EMA decay), each loss group summed over its terms,
    the consistency loss and its matched pairs, the pseudo-labels and 2D ignore regions of the
    batch, and each modality's supervised + pseudo-label loss."""
    record: dict[str, float] = {"loss": loss.item(), **optimised}
    record.update({name: sum(v.item() for v in terms.values()) for name, terms in losses.items()})
    record.update(
        consistency=consistency.item(),
        consistency_pairs=pairs,
        pseudo_labels_3d=sum(len(p.labels_3d) for p in pseudo),
        pseudo_labels_2d=sum(len(p.labels_2d) for p in pseudo),
        ignored_2d=sum(len(p.ignore_2d) for p in pseudo),
        loss_2d=record["supervised_2d"] + record["pseudo_2d"],
        loss_3d=record["supervised_3d"] + record["pseudo_3d"],
    )
    return record


class TeacherStudentTrainer(SupervisedTrainer):
    """Students and EMA teachers start from pre-trained weights ([ssl] pretrained); the teachers
    are the run's output. Trained on labeled frames alone, this is the labeled-only control:
    the teacher-student schedule and EMA without any unlabeled loss."""

    def __init__(
        self, config: ExperimentConfig, run_dir: Path, context: DistributedContext
    ) -> None:
        if config.ssl.method == "labeled-only":
            raise ValueError("labeled-only training uses SupervisedTrainer")
        super().__init__(config, run_dir, context)
        if config.ssl.pretrained:
            pretrained = load_checkpoint(resolve_checkpoint(Path(config.ssl.pretrained)))
            self.state.model_2d.load_state_dict(pretrained["model_2d"])
            load_pretrained(self.state.model_3d, pretrained["model_3d"])
        self.state.teacher_2d = _frozen_copy(self.state.model_2d)
        self.state.teacher_3d = _frozen_copy(self.state.model_3d)

    def update_teachers(self, step: int) -> float:
        """theta_T <- d theta_T + (1 - d) theta_S after optimiser step `step` (counted from 0);
        returns d."""
        ssl = self.config.ssl
        decay = ema_decay(step, ssl.ema_offset, ssl.ema_max_decay)
        ema_update(self.state.teacher_2d, self.state.model_2d, decay)
        ema_update(self.state.teacher_3d, self.state.model_3d, decay)
        return decay

    def train_step(self, batch: Batch) -> dict[str, float]:
        record = super().train_step(batch)
        record["ema_decay"] = self.update_teachers(self.state.step - 1)
        return record


class SemiSupervisedTrainer(TeacherStudentTrainer):
    """Confidence-thresholding or DetMatch training from pre-trained weights."""

    def __init__(
        self, config: ExperimentConfig, run_dir: Path, context: DistributedContext
    ) -> None:
        super().__init__(config, run_dir, context)
        ssl, data = config.ssl, config.data
        frames = FrameDataset(
            data.root, ssl.unlabeled_split, data.classes, data.image_size, self.train_set.grid,
            augment=True, flip_probability=config.train.flip_probability,
            seed=config.train.seed + 1, with_labels=False,
        )  # fmt: skip
        self.unlabeled_set = UnlabeledDataset(
            frames, ssl.student_rotation, ssl.student_scale, photometric=ssl.photometric
        )
        self.rule = pseudo_label_rule(ssl)
        self.consistency = ConsistencyWeights(
            class_weight=ssl.consistency_class_weight,
            l1_weight=ssl.consistency_l1_weight,
            giou_weight=ssl.consistency_giou_weight,
            use_class=ssl.consistency_class,
            use_box=ssl.consistency_box,
        )

    @property
    def data_workers(self) -> int:
        return 2 * self.config.data.num_workers  # the labeled and the unlabeled loader

    def batches(self) -> Iterator[tuple[Batch, UnlabeledBatch]]:
        labeled = super().batches()
        unlabeled = iter(
            self.loader(self.unlabeled_set, collate_unlabeled, self.config.train.seed + 1)
        )
        return zip(labeled, unlabeled, strict=False)

    def train_step(self, item: tuple[Batch, UnlabeledBatch]) -> dict[str, float]:
        labeled, unlabeled = item[0].to(self.device), item[1].to(self.device)
        state, ssl, n = self.state, self.config.ssl, len(labeled)
        student_2d, student_3d, weak = state.model_2d, state.model_3d, unlabeled.weak

        # 1. Teachers predict on the weak views; detections come back un-augmented.
        detections = predict_batch(state.teacher_2d, state.teacher_3d, weak, self.autocast_dtype)

        # 2. Pseudo-labels by the method's rule, then moved into the students' frames.
        pseudo = [
            self.rule.frame_labels(d2, d3, s.calib, s.image_transform.original_size)
            for s, (d2, d3) in zip(weak.samples, detections, strict=True)
        ]
        pseudo_2d, pseudo_3d = pseudo_label_targets(student_2d, student_3d, unlabeled, pseudo)

        # 3. Students: one forward each over the labeled frames and the strong unlabeled views.
        student_2d.train()
        student_3d.train()
        images, pillars = unlabeled.student_inputs(labeled)
        labeled_2d, unlabeled_2d = split_outputs(self.run_2d(images), n)
        labeled_3d, unlabeled_3d = split_outputs(self.run_3d(pillars), n)
        targets_2d, targets_3d = ground_truth_targets(student_2d, student_3d, labeled.samples)
        losses = {
            "supervised_2d": student_2d.loss(labeled_2d, targets_2d),
            "supervised_3d": student_3d.loss(labeled_3d, targets_3d),
            # The 2D pseudo-label loss is classification only (Unbiased Teacher).
            "pseudo_2d": student_2d.loss(unlabeled_2d, pseudo_2d, box_regression=False),
            "pseudo_3d": student_3d.loss(unlabeled_3d, pseudo_3d),
        }
        loss = (
            _total(losses["supervised_2d"])
            + _total(losses["supervised_3d"])
            + ssl.pseudo_label_weight
            * (self.rule.weight_2d * _total(losses["pseudo_2d"]) + _total(losses["pseudo_3d"]))
        )

        # 4. DetMatch: the 2D teacher's matched boxes pull the 3D student's projections
        # (matched with the rule's own tau_hung).
        consistency, pairs = torch.zeros(()), 0
        if self.rule.consistency:
            consistency, pairs = consistency_loss(
                student_3d, unlabeled_3d, weak.samples, unlabeled.student_clouds,
                [p.consistency_2d for p in pseudo], self.consistency, self.rule.policy.tau_hung,
            )  # fmt: skip
            loss = loss + consistency

        # 5. Optimiser steps; the teachers follow the students.
        optimised = self.optimise(loss)
        optimised["ema_decay"] = self.update_teachers(state.step - 1)
        return step_record(loss, optimised, losses, consistency, pairs, pseudo)


def trainer_type(method: str) -> type[SupervisedTrainer]:
    """The trainer of an [ssl] method."""
    trainers = {
        "labeled-only": SupervisedTrainer,
        "labeled-only-control": TeacherStudentTrainer,
        "confidence": SemiSupervisedTrainer,
        "detmatch": SemiSupervisedTrainer,
    }
    return trainers[method]
