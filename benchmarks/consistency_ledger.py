"""A gradient ledger of the 3D student's box regression under DetMatch (issue 14, E2).

    python benchmarks/consistency_ledger.py --checkpoint runs/ssl_s0/pretrain \
        --data data/synth2k --split train_dev0.1 [--batches 10] [--set ssl.KEY=VALUE ...]

On labeled frames used as the unlabeled stream (never val): the pre-trained weights as teacher
and student, the student on the strong views. For each loss term that reaches the dense box
regression (the labels' supervised regression, the 3D pseudo-label regression, the
consistency loss's L1 and GIoU terms), the gradient with respect to the regression map at the
cells the consistency loss matched: mean |gradient| and mean signed gradient per channel
(x, y offsets, z, log l, log w, log h, sin, cos yaw). Also the share of matched cells that are
not the matched object's centre cell, where nothing but the consistency loss trains the
regression. Prints a table and the command to rerun it.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from detmatch.config import apply_overrides
from detmatch.data.dataset import FrameDataset
from detmatch.data.unlabeled import UnlabeledDataset, collate_unlabeled
from detmatch.inference import predict_batch
from detmatch.models.build import load_detectors
from detmatch.models.contract import forward_pillars
from detmatch.training.consistency import ConsistencyWeights, consistency_loss
from detmatch.training.rules import pseudo_label_rule
from detmatch.training.semi_supervised import pseudo_label_targets

CHANNELS = ("dx", "dy", "z", "log_l", "log_w", "log_h", "sin", "cos")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", required=True, help="pre-trained run or checkpoint")
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", required=True, help="labeled frames (dev), never val")
    parser.add_argument("--batches", type=int, default=10)
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args()
    loaded = load_detectors(args.checkpoint)
    # The ledger measures the box term: on here whatever the run's config (off by default).
    overrides = [*args.set, "ssl.method=detmatch", "ssl.consistency_box=true"]
    config = apply_overrides(loaded.config, overrides)
    data, ssl = config.data, config.ssl
    teacher_2d, teacher_3d = loaded.model_2d, loaded.model_3d
    student = load_detectors(args.checkpoint).model_3d.train()
    frames = FrameDataset(args.data, args.split, data.classes, data.image_size, student.grid,
                          augment=True, seed=1, projected_2d=True)  # fmt: skip
    views = UnlabeledDataset(frames, ssl.student_rotation, ssl.student_scale)
    rule = pseudo_label_rule(ssl)
    weights = ConsistencyWeights(
        class_weight=0.0, l1_weight=ssl.consistency_l1_weight,
        giou_weight=ssl.consistency_giou_weight, use_class=False, use_box=True,
        reduction=ssl.consistency_reduction, nms=ssl.consistency_nms,
    )  # fmt: skip
    sums = {name: np.zeros((2, len(CHANNELS))) for name in ("supervised", "pseudo-label",
                                                            "consistency")}  # fmt: skip
    cells = off_centre = 0
    rng = np.random.default_rng(0)
    order = rng.permutation(len(frames))
    for start in range(0, min(args.batches * 4, len(frames)), 4):
        items = [views[(int(i), int(i))] for i in order[start : start + 4]]
        batch = collate_unlabeled(items)
        detections = predict_batch(teacher_2d, teacher_3d, batch.weak)
        pseudo = [rule.frame_labels(d2, d3, s.calib, s.image_transform.original_size)
                  for s, (d2, d3) in zip(batch.weak.samples, detections, strict=True)]  # fmt: skip
        _, pseudo_3d = pseudo_label_targets(teacher_2d, student, batch, pseudo)
        # The labels (weak frame) moved into the student's frame, as supervised targets.
        supervised = [
            student.build_targets(
                sample.gt_3d.map_boxes(lambda b, s=sample, c=cloud: c.apply_boxes(
                    s.cloud.invert_boxes(b)))
            )
            for sample, cloud in zip(batch.weak.samples, batch.student_clouds, strict=True)
        ]  # fmt: skip
        heatmap, regression = forward_pillars(student, batch.student_pillars)
        regression.retain_grad()
        terms = {
            "supervised": student.loss((heatmap, regression), supervised)["regression"],
            "pseudo-label": student.loss((heatmap, regression), pseudo_3d)["regression"],
            "consistency": consistency_loss(
                student, (heatmap, regression), batch.weak.samples, batch.student_clouds,
                [p.consistency_2d for p in pseudo], weights, ssl.tau_hung,
            )[0],
        }  # fmt: skip
        grads = {}
        for name, term in terms.items():
            (grad,) = torch.autograd.grad(term, regression, retain_graph=True, allow_unused=True)
            grads[name] = torch.zeros_like(regression) if grad is None else grad
        matched = grads["consistency"].abs().sum(dim=1) > 0  # (B, h, w) the matched cells
        if not matched.any():
            continue
        for name, grad in grads.items():
            at = grad.permute(0, 2, 3, 1)[matched].double().numpy()  # (cells, 8)
            sums[name][0] += np.abs(at).sum(axis=0)
            sums[name][1] += at.sum(axis=0)
        centres = torch.zeros_like(matched)
        for b, target in enumerate(supervised):
            centres[b].view(-1)[torch.from_numpy(target.index)] = True
        cells += int(matched.sum())
        off_centre += int((matched & ~centres).sum())
    if cells == 0:
        print("no consistency matches: nothing to report")
        return
    print(f"{cells} matched cells over {args.batches} batches of 4 frames ({args.split}); "
          f"{off_centre / cells:.0%} are not the matched object's centre cell")  # fmt: skip
    print("| term | " + " | ".join(CHANNELS) + " |")
    print("|---|" + "---|" * len(CHANNELS))
    for name, (absolute, signed) in sums.items():
        print(f"| {name} mean abs | " + " | ".join(f"{v / cells:.2e}" for v in absolute) + " |")
        print(f"| {name} mean signed | " + " | ".join(f"{v / cells:+.2e}" for v in signed) + " |")
    ratio = sums["consistency"][0] / np.maximum(sums["supervised"][0], 1e-12)
    print("| consistency / supervised | " + " | ".join(f"{v:.2f}" for v in ratio) + " |")
    print("rerun: python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
