"""The benchmark's stand-in for the paper's COCO pre-training: a 2D detector trained on every
label of a separate synthetic set (another generator seed: no frame, seed or scene of the
benchmark's data), loaded as the 2D detector's starting weights ([train] init_2d) by every
method alike, as the paper's methods all start from COCO. It is kinder than COCO is for KITTI
(same domain, same classes); BENCHMARKS.md says so wherever it is used.

    detmatch synth --out data/synth_cam_v2 --frames 600 --seed 7 --world v2 --workers 2
    python -m benchmarks.camera_init --data data/synth_cam_v2 --out runs/camera_v2

`ssl_benchmark --camera-data DIR --camera-run RUN` trains it first (resuming, skipped once
finished) and starts every method's pre-training from it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from benchmarks.harness import benchmark_parser, rerun
from detmatch.checkpoints import list_checkpoints
from detmatch.config import DEVICES, ExperimentConfig, apply_overrides, load_config
from detmatch.data.dataset import Batch
from detmatch.data.synth.world import read_resolution, synth_record
from detmatch.training.distributed import DistributedContext, init_distributed
from detmatch.training.evaluation import evaluate_detectors
from detmatch.training.trainer import SupervisedTrainer

DEFAULT_STEPS = 2000


class CameraTrainer(SupervisedTrainer):
    """SupervisedTrainer with the 3D detector left untouched: 2D loss, 2D step, 2D scores."""

    def train_step(self, batch: Batch) -> dict[str, float]:
        state = self.state
        batch = batch.to(self.device)
        state.model_2d.train()
        targets = [
            state.model_2d.build_targets(s.gt_2d, s.image_transform.input_size)
            for s in batch.samples
        ]
        losses = state.model_2d.loss(self.run_2d(batch.images), targets)
        loss = sum(losses.values())
        record = self.optimise(loss)  # the 3D detector has no gradients: AdamW skips it
        record.update({f"loss_2d/{k}": v.item() for k, v in losses.items()})
        record.update(loss_2d=loss.item(), loss_3d=0.0)
        return record

    def evaluate(self) -> dict[str, Any]:
        scores = evaluate_detectors(
            self.state.model_2d, self.state.model_3d, self.val_set, self.config.data.classes,
            batch_size=self.config.train.batch_size,
        )  # fmt: skip
        return {"2d": scores["2d"], "full_2d": scores["full_2d"]}


def synth_seed(root: Path) -> int:
    """The generator seed in a synthetic data set's synth.json."""
    record = synth_record(root)
    if not record:
        raise SystemExit(f"{root} has no synth.json: the camera's set must be synthetic")
    return int(record["seed"])


def check_disjoint(camera_data: Path, benchmark_data: Path) -> None:
    """Refuse a camera set made with the benchmark data's generator seed (it would hold the
    benchmark's own scenes: frame i depends only on the seed and i), or rendered at another
    camera resolution (the stand-in would start from another camera)."""
    if synth_seed(camera_data) == synth_seed(benchmark_data):
        raise SystemExit(
            f"{camera_data} and {benchmark_data} share generator seed "
            f"{synth_seed(camera_data)}: the camera's set must hold none of the benchmark's "
            "scenes (make it with another --seed)"
        )
    ours, theirs = read_resolution(camera_data), read_resolution(benchmark_data)
    if ours != theirs:
        raise SystemExit(
            f"{camera_data} is rendered at {ours} resolution and {benchmark_data} at {theirs}: "
            "make the camera's set with the benchmark's --resolution"
        )


def camera_config(base: ExperimentConfig, camera_data: Path, steps: int) -> ExperimentConfig:
    """The stand-in's run: the base recipe on every train label of camera_data, scored on its
    val split, from scratch."""
    config = base.replace(
        "data", root=str(camera_data), train_split="train", val_split="val"
    ).replace("train", steps=steps, eval_every=steps, init_2d="")
    return config.replace("train", checkpoint_every=min(config.train.checkpoint_every, steps))


def train_camera_init(
    base: ExperimentConfig,
    camera_data: Path,
    run_dir: Path,
    context: DistributedContext,
    steps: int = DEFAULT_STEPS,
) -> Path:
    """Train the stand-in (resuming; nothing when finished); returns its last checkpoint."""
    config = camera_config(base, camera_data, steps)
    found = list_checkpoints(run_dir)
    if not (found and found[-1].name == f"step_{steps:08d}.pt"):
        trainer = CameraTrainer(config, run_dir, context)
        trainer.resume()
        trainer.run()
        found = list_checkpoints(run_dir)
    return found[-1]


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--config", default="configs/ssl_cpu.toml")
    parser.add_argument("--data", required=True, help="the camera's synthetic set")
    parser.add_argument("--out", required=True, help="the 2D-only run directory")
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS)
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--device", default="auto", choices=DEVICES)
    args = parser.parse_args()
    base = apply_overrides(load_config(args.config), args.set)
    path = train_camera_init(
        base, Path(args.data), Path(args.out), init_distributed(args.device), args.steps
    )
    print(f"camera stand-in: {path}")
    print(f"rerun: {rerun('camera_init')}")


if __name__ == "__main__":
    main()
