"""Fully supervised accuracy of both detectors on a synthetic set, within a stated CPU budget.

    detmatch synth --out data/synth2k --frames 2000 --seed 0 --workers 2
    python -m benchmarks.supervised_accuracy --config configs/synth_cpu.toml --data data/synth2k \
        --out runs/supervised_cpu
    # the ceiling of the semi-supervised benchmark: its pre-training recipe on every train label
    python -m benchmarks.supervised_accuracy --config configs/ssl_cpu.toml --data data/synth2k \
        --out runs/ceiling --set data.train_split=train --set data.val_split=val \
        --set train.eval_every=3000

Trains with every train-split label (the config's [train] steps), then evaluates the final
model on the val split with the project's KITTI evaluator: moderate R40 AP per class, 2D
(bbox, against the annotated 2D boxes) and 3D (3D and BEV). Prints the table, the wall and
CPU time of training, and the command to rerun. --resume continues an interrupted run.
"""

from __future__ import annotations

import json
import resource
import time
from pathlib import Path

from benchmarks.harness import benchmark_parser, rerun
from detmatch.config import apply_overrides, load_config
from detmatch.training.distributed import init_distributed
from detmatch.training.trainer import SupervisedTrainer


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime + children.ru_utime + children.ru_stime


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--resume", action="store_true")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="config override (repeatable)")  # fmt: skip
    args = parser.parse_args()

    config = apply_overrides(load_config(args.config), args.set).replace("data", root=args.data)
    trainer = SupervisedTrainer(config, Path(args.out), init_distributed())
    if args.resume:
        trainer.resume()
    wall, cpu = time.perf_counter(), cpu_seconds()
    trainer.run()
    wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    metrics = trainer.evaluate() if not trainer.state.metrics else trainer.state.metrics
    classes = config.data.classes
    frames = len(trainer.train_set)
    train = config.train
    print(f"train frames {frames}, val frames {len(trainer.val_set)}")
    print(
        f"steps {train.steps} x batch {train.batch_size} = {train.steps * train.batch_size} frames"
    )
    print(
        f"training wall {wall / 60:.1f} min, CPU {cpu / 60:.1f} min (this process and its workers)"
    )
    print("| modality | " + " | ".join(classes) + " | mAP |")
    print("|---|" + "---|" * (len(classes) + 1))
    for key, label in (("2d", "2D bbox"), ("bev", "BEV"), ("3d", "3D")):
        row = metrics[key]
        print(
            f"| {label} | "
            + " | ".join(f"{row[c]:.1f}" for c in classes)
            + f" | {row['mAP']:.1f} |"
        )
    summary = {k: metrics[k] for k in ("2d", "bev", "3d")}
    summary.update(wall_s=round(wall, 1), cpu_s=round(cpu, 1), train_frames=frames)
    (Path(args.out) / "benchmark.json").write_text(json.dumps(summary, indent=2))
    print(f"rerun: {rerun('supervised_accuracy')}")


if __name__ == "__main__":
    main()
