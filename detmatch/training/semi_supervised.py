"""Teacher-student training: confidence thresholding and DetMatch (DESIGN.md section 3).

Each step takes equal numbers of labeled and unlabeled frames. The step reads like the method:
teacher predictions on the weak views, pseudo-labels (thresholded or 2D-3D matched) in the
un-augmented frame, moved into the students' frames, student losses (supervised + pseudo-label
+ consistency), optimiser steps, EMA update of the teachers.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from detmatch.config import ExperimentConfig
from detmatch.data.dataset import Batch, FrameDataset
from detmatch.data.unlabeled import UnlabeledBatch, UnlabeledDataset, collate_unlabeled
from detmatch.inference import predict_batch
from detmatch.pseudo_labels import confident_detections, match_detections
from detmatch.structures import Detections
from detmatch.training.checkpoint import load_checkpoint, resolve_checkpoint
from detmatch.training.consistency import ConsistencyWeights, TeacherTargets2D, consistency_loss
from detmatch.training.distributed import DistributedContext
from detmatch.training.ema import ema_decay, ema_update
from detmatch.training.trainer import (
    SupervisedTrainer,
    clip_and_step,
    ground_truth_targets,
    warmup_factor,
)


@dataclass(frozen=True)
class FramePseudoLabels:
    """One unlabeled frame's pseudo-labels in the students' frames.

    boxes_3d (N, 7) student LiDAR frame and classes_3d; boxes_2d (M, 4) student input pixels
    and classes_2d; teacher_2d: the matched 2D teacher boxes in original pixels for the
    consistency loss (DetMatch only, else empty).
    """

    boxes_3d: np.ndarray
    classes_3d: np.ndarray
    boxes_2d: np.ndarray
    classes_2d: np.ndarray
    teacher_2d: TeacherTargets2D


def _frozen_copy(model: torch.nn.Module) -> torch.nn.Module:
    teacher = copy.deepcopy(model).eval()
    for parameter in teacher.parameters():
        parameter.requires_grad_(False)
    return teacher


class SemiSupervisedTrainer(SupervisedTrainer):
    """Confidence-thresholding or DetMatch training from pre-trained weights."""

    def __init__(
        self, config: ExperimentConfig, run_dir: Path, context: DistributedContext
    ) -> None:
        if config.ssl.method == "labeled-only":
            raise ValueError("labeled-only training uses SupervisedTrainer")
        super().__init__(config, run_dir, context)
        ssl, data = config.ssl, config.data
        if ssl.pretrained:
            pretrained = load_checkpoint(resolve_checkpoint(Path(ssl.pretrained)))
            self.state.model_2d.load_state_dict(pretrained["model_2d"])
            self.state.model_3d.load_state_dict(pretrained["model_3d"])
        self.state.teacher_2d = _frozen_copy(self.state.model_2d)
        self.state.teacher_3d = _frozen_copy(self.state.model_3d)
        frames = FrameDataset(
            data.root, ssl.unlabeled_split, data.classes, data.image_size, self.train_set.grid,
            augment=True, flip_probability=config.train.flip_probability,
            seed=config.train.seed + 1, with_labels=False,
        )  # fmt: skip
        self.unlabeled_set = UnlabeledDataset(
            frames, ssl.student_rotation, ssl.student_scale, photometric=ssl.photometric
        )
        self.consistency = ConsistencyWeights(
            class_weight=ssl.consistency_class_weight,
            l1_weight=ssl.consistency_l1_weight,
            giou_weight=ssl.consistency_giou_weight,
            use_class=ssl.consistency_class,
            use_box=ssl.consistency_box,
        )

    def batches(self) -> Iterator[tuple[Batch, UnlabeledBatch]]:
        labeled = super().batches()
        unlabeled = iter(
            self.loader(self.unlabeled_set, collate_unlabeled, self.config.train.seed + 1)
        )
        return zip(labeled, unlabeled, strict=False)

    def pseudo_labels(
        self, batch: UnlabeledBatch, detections: list[tuple[Detections, Detections]]
    ) -> list[FramePseudoLabels]:
        """Teacher detections (un-augmented frame) -> pseudo-labels in the students' frames."""
        ssl = self.config.ssl
        labels = []
        for b, (detections_2d, detections_3d) in enumerate(detections):
            sample = batch.weak.samples[b]
            num_classes = detections_2d.probabilities.shape[1]
            teacher_2d = TeacherTargets2D(
                np.zeros((0, 4)), np.zeros(0, dtype=np.int64), np.zeros((0, num_classes))
            )
            if ssl.method == "confidence":
                confident_3d = confident_detections(detections_3d, ssl.tau_3d)
                confident_2d = confident_detections(detections_2d, ssl.tau_2d)
                boxes_3d, classes_3d = confident_3d.boxes, confident_3d.classes
                boxes_2d, classes_2d = confident_2d.boxes, confident_2d.classes
            else:
                matched = match_detections(
                    detections_3d, detections_2d, sample.calib,
                    sample.image_transform.original_size, tau_hung=ssl.tau_hung,
                    tau_3d_outside_view=ssl.tau_3d if ssl.fov_fallback else None,
                )  # fmt: skip
                pairs = matched.matched
                boxes_3d, classes_3d = matched.boxes_3d, matched.class_3d
                boxes_2d, classes_2d = matched.boxes_2d[pairs], matched.class_2d[pairs]
                teacher_2d = TeacherTargets2D(
                    boxes_2d, classes_2d, detections_2d.probabilities[matched.index_2d[pairs]]
                )
            labels.append(
                FramePseudoLabels(
                    boxes_3d=batch.student_clouds[b].apply_boxes(boxes_3d),
                    classes_3d=np.asarray(classes_3d, dtype=np.int64),
                    boxes_2d=sample.image_transform.apply(boxes_2d),
                    classes_2d=np.asarray(classes_2d, dtype=np.int64),
                    teacher_2d=teacher_2d,
                )
            )
        return labels

    def train_step(self, item: tuple[Batch, UnlabeledBatch]) -> dict[str, float]:
        labeled, unlabeled = item[0].to(self.device), item[1].to(self.device)
        state, ssl, train = self.state, self.config.ssl, self.config.train
        student_2d, student_3d = state.model_2d, state.model_3d
        n = len(labeled)

        # 1. Teachers predict on the weak views; detections come back un-augmented.
        detections = predict_batch(state.teacher_2d, state.teacher_3d, unlabeled.weak)

        # 2. Pseudo-labels: thresholded (confidence) or 2D-3D matched (DetMatch).
        pseudo = self.pseudo_labels(unlabeled, detections)

        # 3. Students: one forward each over labeled + strongly augmented unlabeled frames.
        student_2d.train()
        student_3d.train()
        heat_2d, size_2d, offset_2d = self.forward_2d(
            torch.cat([labeled.images, unlabeled.student_images])
        )
        shifted = unlabeled.student_pillar_coords.clone()
        shifted[:, 0] += n
        heat_3d, regression_3d = self.forward_3d(
            torch.cat([labeled.pillar_features, unlabeled.student_pillar_features]),
            torch.cat([labeled.pillar_coords, shifted]),
            torch.cat([labeled.pillar_counts, unlabeled.student_pillar_counts]),
            batch_size=2 * n,
        )
        targets_2d, targets_3d = ground_truth_targets(student_2d, student_3d, labeled.samples)
        supervised_2d = student_2d.loss((heat_2d[:n], size_2d[:n], offset_2d[:n]), targets_2d)
        supervised_3d = student_3d.loss((heat_3d[:n], regression_3d[:n]), targets_3d)
        input_size = labeled.samples[0].image_transform.input_size
        # The 2D pseudo-label loss is classification only (Unbiased Teacher).
        pseudo_2d = student_2d.loss(
            (heat_2d[n:], size_2d[n:], offset_2d[n:]),
            [student_2d.build_targets(p.boxes_2d, p.classes_2d, input_size) for p in pseudo],
            box_regression=False,
        )
        pseudo_3d = student_3d.loss(
            (heat_3d[n:], regression_3d[n:]),
            [student_3d.build_targets(p.boxes_3d, p.classes_3d) for p in pseudo],
        )
        weight_2d = ssl.detmatch_2d_pseudo_weight if ssl.method == "detmatch" else 1.0
        loss = (
            sum(supervised_2d.values())
            + sum(supervised_3d.values())
            + ssl.pseudo_label_weight
            * (weight_2d * sum(pseudo_2d.values()) + sum(pseudo_3d.values()))
        )
        consistency, pairs = heat_3d.sum() * 0.0, 0
        if ssl.method == "detmatch" and (ssl.consistency_class or ssl.consistency_box):
            samples = unlabeled.weak.samples
            consistency, pairs = consistency_loss(
                student_3d, heat_3d[n:], regression_3d[n:], unlabeled.student_clouds,
                [s.calib for s in samples], [s.image_transform.original_size for s in samples],
                [p.teacher_2d for p in pseudo], self.consistency, ssl.tau_hung,
            )  # fmt: skip
            loss = loss + consistency

        state.optimizer_2d.zero_grad(set_to_none=True)
        state.optimizer_3d.zero_grad(set_to_none=True)
        loss.backward()
        factor = warmup_factor(state.step, train.warmup_steps)
        grad_2d = clip_and_step(
            state.optimizer_2d, student_2d, train.grad_clip, train.lr_2d * factor
        )
        grad_3d = clip_and_step(
            state.optimizer_3d, student_3d, train.grad_clip, train.lr_3d * factor
        )

        # 4. The teachers follow the students.
        decay = ema_decay(state.step, ssl.ema_offset, ssl.ema_max_decay)
        ema_update(state.teacher_2d, student_2d, decay)
        ema_update(state.teacher_3d, student_3d, decay)
        state.step += 1

        record: dict[str, Any] = {"loss": loss.item(), "ema_decay": decay}
        for prefix, losses in (
            ("supervised_2d", supervised_2d), ("supervised_3d", supervised_3d),
            ("pseudo_2d", pseudo_2d), ("pseudo_3d", pseudo_3d),
        ):  # fmt: skip
            record[prefix] = sum(v.item() for v in losses.values())
        record.update(consistency=consistency.item(), consistency_pairs=pairs)
        record.update(pseudo_labels_3d=sum(len(p.boxes_3d) for p in pseudo))
        record.update(pseudo_labels_2d=sum(len(p.boxes_2d) for p in pseudo))
        record.update(grad_norm_2d=grad_2d, grad_norm_3d=grad_3d)
        record.update(lr_2d=train.lr_2d * factor, lr_3d=train.lr_3d * factor)
        record.update(loss_2d=record["supervised_2d"] + record["pseudo_2d"])
        record.update(loss_3d=record["supervised_3d"] + record["pseudo_3d"])
        return record
