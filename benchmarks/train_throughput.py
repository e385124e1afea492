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
from detmatch.models.detector2d import CenterNet2D
from detmatch.models.detector3d import PointPillars3D
from detmatch.models.pillars import pillarize


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
    classes = len(config.data.classes)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    width, height = config.data.image_size

    model_2d = CenterNet2D(config.detector2d, classes).train()
    images = torch.rand(args.batch, 3, height, width) * 255
    targets_2d = [
        model_2d.build_targets(np.array([[50.0, 40, 120, 90]]), np.array([0]), (width, height))
    ] * args.batch

    def step_2d() -> None:
        model_2d.zero_grad()
        sum(model_2d.loss(model_2d(images), targets_2d).values()).backward()

    model_3d = PointPillars3D(config.detector3d, classes).train()
    pillars = [pillarize(random_cloud(rng), model_3d.grid) for _ in range(args.batch)]
    features = torch.from_numpy(np.concatenate([p[0] for p in pillars]))
    coords = torch.from_numpy(
        np.concatenate(
            [np.column_stack([np.full(len(p[1]), b), p[1]]) for b, p in enumerate(pillars)]
        )
    )
    counts = torch.from_numpy(np.concatenate([p[2] for p in pillars]))
    targets_3d = [
        model_3d.build_targets(np.array([[20.0, 2, -0.9, 3.9, 1.6, 1.5, 0.3]]), np.array([0]))
    ] * args.batch

    def step_3d() -> None:
        model_3d.zero_grad()
        outputs = model_3d(features, coords, counts, batch_size=args.batch)
        sum(model_3d.loss(outputs, targets_3d).values()).backward()

    cloud = random_cloud(rng)
    start = time.perf_counter()
    for _ in range(args.iters):
        pillarize(cloud, model_3d.grid)
    pillarize_ms = (time.perf_counter() - start) / args.iters * 1000

    with torch.no_grad(), FlopCounterMode(display=False) as flops_2d:
        model_2d.eval()(images[:1])
    with torch.no_grad(), FlopCounterMode(display=False) as flops_3d:
        one = coords[:, 0] == 0
        model_3d.eval()(features[one], coords[one], counts[one], batch_size=1)
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
