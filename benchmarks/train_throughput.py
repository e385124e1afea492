"""Training throughput (forward + backward, frames/s) of each detector on this machine's CPU,
with parameter counts and forward FLOPs per frame.

    python benchmarks/train_throughput.py --config configs/synth_cpu.toml [--batch 4] [--iters 10]

Inputs are synthetic tensors of the config's sizes; the 3D input is a point cloud of a
typical synthetic frame pillarized with the config's grid (about 60k points in range).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from detmatch.config import load_config
from detmatch.data.dataset import collate_pillars
from detmatch.models.build import build_detectors
from detmatch.models.contract import forward_pillars
from detmatch.models.pillars import pillarize
from detmatch.structures import LabeledBoxes


def random_cloud(rng: np.random.Generator, count: int = 60000) -> np.ndarray:
    """A ground plane plus vertical structures: roughly the occupancy of a synthetic frame."""
    ground = np.column_stack(
        [
            rng.uniform(0, 70, count // 2),
            rng.uniform(-35, 35, count // 2),
            rng.normal(-1.7, 0.03, count // 2),
        ]
    )
    side = rng.choice([-12.0, 12.0], count // 2) + rng.normal(0, 0.2, count // 2)
    walls = np.column_stack(
        [rng.uniform(0, 70, count // 2), side, rng.uniform(-1.7, 2.0, count // 2)]
    )
    points = np.concatenate([ground, walls])
    return np.column_stack([points, rng.uniform(0, 1, len(points))]).astype(np.float32)


def measure(step, iters: int) -> float:
    step()  # warm-up
    start = time.perf_counter()
    for _ in range(iters):
        step()
    return (time.perf_counter() - start) / iters


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--iters", type=int, default=10)
    args = parser.parse_args()
    config = load_config(args.config)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    width, height = config.data.image_size

    model_2d, model_3d = (model.train() for model in build_detectors(config))
    images = torch.rand(args.batch, 3, height, width) * 255
    box_2d = LabeledBoxes(np.array([[50.0, 40, 120, 90]]), np.array([0]))
    targets_2d = [model_2d.build_targets(box_2d, (width, height))] * args.batch

    def step_2d() -> None:
        model_2d.zero_grad()
        sum(model_2d.loss(model_2d(images), targets_2d).values()).backward()

    pillars = collate_pillars([pillarize(random_cloud(rng), model_3d.grid) for _ in images])
    box_3d = LabeledBoxes(np.array([[20.0, 2, -0.9, 3.9, 1.6, 1.5, 0.3]]), np.array([0]))
    targets_3d = [model_3d.build_targets(box_3d)] * args.batch

    def step_3d() -> None:
        model_3d.zero_grad()
        outputs = forward_pillars(model_3d, pillars)
        sum(model_3d.loss(outputs, targets_3d).values()).backward()

    cloud = random_cloud(rng)
    start = time.perf_counter()
    for _ in range(args.iters):
        pillarize(cloud, model_3d.grid)
    pillarize_ms = (time.perf_counter() - start) / args.iters * 1000

    with torch.no_grad(), FlopCounterMode(display=False) as flops_2d:
        model_2d.eval()(images[:1])
    with torch.no_grad(), FlopCounterMode(display=False) as flops_3d:
        one = pillars.coords[:, 0] == 0
        model_3d.eval()(pillars.features[one], pillars.coords[one], pillars.counts[one])
    model_2d.train()
    model_3d.train()
    seconds_2d = measure(step_2d, args.iters)
    seconds_3d = measure(step_3d, args.iters)

    print(f"config {args.config}; batch {args.batch}; torch threads {torch.get_num_threads()}")
    print("| model | parameters | forward GFLOPs/frame | train frames/s (fwd+bwd) |")
    print("|---|---|---|---|")
    for name, model, flops, seconds in (
        ("2D CenterNet", model_2d, flops_2d, seconds_2d),
        ("3D PointPillars", model_3d, flops_3d, seconds_3d),
    ):
        parameters = sum(p.numel() for p in model.parameters())
        print(
            f"| {name} | {parameters / 1e6:.2f} M | {flops.get_total_flops() / 1e9:.2f} | "
            f"{args.batch / seconds:.1f} |"
        )
    print(f"pillarize (numpy, one frame of {len(cloud)} points): {pillarize_ms:.1f} ms")
    print("rerun: python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
