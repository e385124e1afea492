"""Pre-train the camera (2D) detector alone, scored on dev, and pair it with the 3D detector of
a finished labeled-only run: a 2D design is decided in the time of its own training.

In labeled-only pre-training the two detectors share frames but nothing else (their own
losses, optimisers and parameters), so a 2D-only run with another [detector2d] or [data]
image_size, paired with an earlier run's 3D detector, is a pre-training run of the new
design. The pair is written as RUN/checkpoints/step_N.pt plus a learning curve, ready to be
`ssl_benchmark.py --out OUT`'s OUT/pretrain (the benchmark then trains only the methods).

    python -m benchmarks.camera_pretrain --config configs/ssl_cpu.toml --data data/synth2k \
        --split train_labeled_0.02_s0_dev0.1 --out runs/cam_f02_up2 \
        --set "data.image_size=[1248, 384]" \
        --pair-3d runs/f02_s0/pretrain --paired runs/f02_s0_up2/pretrain
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from detmatch.checkpoints import (
    checkpoint_path,
    list_checkpoints,
    load_checkpoint,
    run_evaluations,
)
from detmatch.config import DEVICES, apply_overrides, config_to_dict, load_config
from detmatch.data.dataset import Batch
from detmatch.training.checkpoint import save_checkpoint
from detmatch.training.distributed import init_distributed
from detmatch.training.evaluation import evaluate_detectors
from detmatch.training.trainer import SupervisedTrainer


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


def pair(camera_run: Path, lidar_run: Path, paired: Path) -> Path:
    """camera_run's 2D detector with lidar_run's 3D detector as a finished pre-training run:
    lidar_run's config with camera_run's [detector2d] and [data] image_size ([train] must be
    the same; the camera may have trained on other frames, e.g. another data set); the
    learning curve joins both runs' dev evaluations at their common steps."""
    camera = load_checkpoint(list_checkpoints(camera_run)[-1])
    lidar = load_checkpoint(list_checkpoints(lidar_run)[-1])
    for section in ("detector3d", "train"):
        if camera["config"][section] != lidar["config"][section]:
            raise SystemExit(f"[{section}] differs between {camera_run} and {lidar_run}")
    if camera["step"] != lidar["step"]:
        raise SystemExit(f"steps differ: {camera['step']} against {lidar['step']}")
    config = dict(lidar["config"], detector2d=camera["config"]["detector2d"])
    config["data"] = dict(config["data"], image_size=camera["config"]["data"]["image_size"])
    checkpoint = dict(
        camera, config=config, model_3d=lidar["model_3d"], optimizer_3d=lidar["optimizer_3d"]
    )
    camera_evals, lidar_evals = run_evaluations(camera_run), run_evaluations(lidar_run)
    checkpoint["metrics"] = {**lidar["metrics"], **camera["metrics"]}
    path = checkpoint_path(paired, camera["step"])
    path.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(path, checkpoint)
    (paired / "config.json").write_text(json.dumps(config, indent=2))
    with (paired / "metrics.jsonl").open("w") as log:
        for step in sorted(set(camera_evals) & set(lidar_evals)):
            joined = {**lidar_evals[step], **camera_evals[step]}
            log.write(json.dumps({"step": step, "eval": joined}) + "\n")
    return path


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", default="configs/ssl_cpu.toml")
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", required=True, help="the labeled split to train on")
    parser.add_argument("--dev", default="train_dev0.1", help="the split scored while training")
    parser.add_argument("--out", required=True, help="the 2D-only run directory")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--device", default="auto", choices=DEVICES)
    parser.add_argument("--pair-3d", help="a finished labeled-only run whose 3D detector to pair")
    parser.add_argument("--paired", help="the paired run directory to write (with --pair-3d)")
    args = parser.parse_args()
    if bool(args.pair_3d) != bool(args.paired):
        parser.error("--pair-3d and --paired go together")
    config = apply_overrides(load_config(args.config), args.set)
    config = config.replace("data", root=args.data, train_split=args.split, val_split=args.dev)
    out = Path(args.out)
    trainer = CameraTrainer(config, out, init_distributed(args.device))
    trainer.resume()
    trainer.run()
    final = trainer.state.metrics["2d"]
    print(json.dumps({"config": config_to_dict(config)["detector2d"], "dev_2d": final}))
    print(f"dev 2D moderate AP: {', '.join(f'{k} {v:.1f}' for k, v in final.items())}")
    if args.pair_3d:
        print(f"paired: {pair(out, Path(args.pair_3d), Path(args.paired))}")


if __name__ == "__main__":
    main()
