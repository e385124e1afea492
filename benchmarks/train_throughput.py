"""Training throughput (forward + backward, frames/s) of each detector on this machine's CPU,
with parameter counts and forward FLOPs per frame.

    python -m benchmarks.train_throughput --config configs/synth_cpu.toml [--data DIR]
        [--batch 4] [--iters 10] [--rounds 3]

Measures the training step before and after the speed-up in one run, alternating: "before" is
fp32 with the pillar encoder on the padded (P, M) layout (the code as it was), "after" is the
config's [train] precision (bf16 autocast where the CPU has it) with the encoder on real
points. Images are random tensors of the config's size; the 3D input is the clouds of --data's
first frames (or generated ground-and-walls clouds of about 60k points).
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from benchmarks.harness import benchmark_parser, rerun
from detmatch.config import load_config
from detmatch.data.dataset import collate_pillars
from detmatch.data.kitti import KittiDataset
from detmatch.models.build import build_detectors
from detmatch.models.contract import forward_pillars
from detmatch.models.pillars import pillarize
from detmatch.precision import autocast, autocast_dtype, fp32
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


def variant_steps(config, batch: int, clouds: list[np.ndarray], fast: bool):
    """(2D step, 3D step, models) of one variant. fast False is the code before the speed-up:
    fp32 forward passes and the pillar encoder on the padded (P, M) layout in training too;
    fast True is today's training: the config's precision, the 2D detector channels-last and
    the encoder on real points."""
    torch.manual_seed(0)
    model_2d, model_3d = (model.train() for model in build_detectors(config))
    if not fast:
        model_3d.encoder.forward = model_3d.encoder._forward_padded
    else:  # as the trainer does
        model_2d.to(memory_format=torch.channels_last)
    dtype = autocast_dtype(config.train.precision, torch.device("cpu")) if fast else None
    width, height = config.data.image_size
    images = torch.rand(batch, 3, height, width) * 255
    if fast:
        images = images.contiguous(memory_format=torch.channels_last)
    box_2d = LabeledBoxes(np.array([[50.0, 40, 120, 90]]), np.array([0]))
    targets_2d = [model_2d.build_targets(box_2d, (width, height))] * batch
    pillars = collate_pillars([pillarize(cloud, model_3d.grid) for cloud in clouds])
    box_3d = LabeledBoxes(np.array([[20.0, 2, -0.9, 3.9, 1.6, 1.5, 0.3]]), np.array([0]))
    targets_3d = [model_3d.build_targets(box_3d)] * batch

    def step_2d() -> None:
        model_2d.zero_grad()
        with autocast(torch.device("cpu"), dtype):
            outputs = fp32(model_2d(images))
        sum(model_2d.loss(outputs, targets_2d).values()).backward()

    def step_3d() -> None:
        model_3d.zero_grad()
        with autocast(torch.device("cpu"), dtype):
            outputs = fp32(forward_pillars(model_3d, pillars))
        sum(model_3d.loss(outputs, targets_3d).values()).backward()

    return step_2d, step_3d, model_2d, model_3d, images, pillars


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--data", help="KITTI-layout directory: pillarize its first frames' "
                        "clouds instead of generated ones")  # fmt: skip
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--iters", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=3,
                        help="alternating before/after measurements (medians)")  # fmt: skip
    args = parser.parse_args()
    config = load_config(args.config)
    rng = np.random.default_rng(0)
    if args.data:
        kitti = KittiDataset(args.data)
        clouds = [kitti.load_frame(i).points for i in kitti.ids()[: args.batch]]
    else:
        clouds = [random_cloud(rng) for _ in range(args.batch)]
    variants = {name: variant_steps(config, args.batch, clouds, fast) for name, fast in
                (("before", False), ("after", True))}  # fmt: skip
    seconds: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.rounds):
        for name, (step_2d, step_3d, *_) in variants.items():
            seconds.setdefault((name, "2d"), []).append(measure(step_2d, args.iters))
            seconds.setdefault((name, "3d"), []).append(measure(step_3d, args.iters))
    median = {key: float(np.median(values)) for key, values in seconds.items()}

    _, _, model_2d, model_3d, images, pillars = variants["after"]
    cloud = clouds[0]
    start = time.perf_counter()
    for _ in range(args.iters):
        pillarize(cloud, model_3d.grid)
    pillarize_ms = (time.perf_counter() - start) / args.iters * 1000
    with torch.no_grad(), FlopCounterMode(display=False) as flops_2d:
        model_2d.eval()(images[:1])
    with torch.no_grad(), FlopCounterMode(display=False) as flops_3d:
        one = pillars.coords[:, 0] == 0
        model_3d.eval()(pillars.features[one], pillars.coords[one], pillars.counts[one])

    precision = config.train.precision
    print(f"config {args.config}; batch {args.batch}; torch threads {torch.get_num_threads()}; "
          f"{len(pillars)} pillars, {int(pillars.counts.sum())} points in the batch; "
          f"{args.rounds} rounds of {args.iters} steps, medians")  # fmt: skip
    print("before: fp32, pillar encoder on the padded layout; after: precision "
          f"{precision!r}, 2D channels-last, pillar encoder on real points")  # fmt: skip
    print("| model | parameters | forward GFLOPs/frame | before frames/s | after frames/s | "
          "speed-up |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for name, model, flops, key in (
        ("2D CenterNet", model_2d, flops_2d, "2d"),
        ("3D PointPillars", model_3d, flops_3d, "3d"),
    ):
        parameters = sum(p.numel() for p in model.parameters())
        before, after = args.batch / median[("before", key)], args.batch / median[("after", key)]
        print(f"| {name} | {parameters / 1e6:.2f} M | {flops.get_total_flops() / 1e9:.2f} | "
              f"{before:.1f} | {after:.1f} | {after / before:.2f}x |")  # fmt: skip
    print(f"pillarize (numpy, one frame of {len(cloud)} points): {pillarize_ms:.1f} ms")
    print(f"rerun: {rerun('train_throughput')}")


if __name__ == "__main__":
    main()
