"""Training and inference: `detmatch train` and `predict`."""

from __future__ import annotations

import argparse
from pathlib import Path

from commands.common import (
    add_device_option,
    add_frame_selection,
    add_overwrite_option,
    frame_selection,
    prepare_output,
    refuse_existing_run,
)
from detmatch.config import METHODS, PRESETS, packaged_configs


def train(args: argparse.Namespace) -> int:
    from detmatch.config import (
        apply_overrides,
        apply_preset,
        load_config,
        refuse_pretraining_overrides,
        teacher_student_config,
    )

    # Before any process of a torchrun job writes (init_distributed is their rendezvous).
    refuse_existing_run(Path(args.out), args.resume)
    config = apply_overrides(load_config(args.config), args.set)
    if args.preset:
        config = apply_preset(config, args.preset)
    if args.data:
        config = config.replace("data", root=args.data)
    if args.method:
        config = config.replace("ssl", method=args.method)
    if args.pretrained:
        config = config.replace("ssl", pretrained=args.pretrained)
    refuse_pretraining_overrides(config, args.set)
    if args.steps is not None:  # the run's length: the stage's for a teacher-student method
        section = "train" if config.ssl.method == "labeled-only" else "ssl"
        config = config.replace(section, steps=args.steps)
    config = teacher_student_config(config)
    if config.ssl.method != "labeled-only" and not config.ssl.pretrained and not args.resume:
        raise ValueError(
            f"--method {config.ssl.method} starts from pre-trained weights: pass --pretrained "
            "CKPT (a labeled-only run) or set [ssl] pretrained"
        )
    from detmatch.training.distributed import init_distributed, shutdown_distributed
    from detmatch.training.semi_supervised import trainer_type

    context = init_distributed(args.device)
    try:
        trainer = trainer_type(config.ssl.method)(config, Path(args.out), context)
        if args.resume and trainer.resume() and context.is_main:
            print(f"resumed {args.out} at step {trainer.state.step}")
        state = trainer.run()
        if context.is_main:
            print(_summary(Path(args.out), state.step, state.metrics, config.data.val_split))
    finally:
        shutdown_distributed()
    return 0


def _summary(out: Path, step: int, metrics: dict, split: str) -> str:
    """Where the run is and its last evaluation, in a few lines (the full figures, per class
    and difficulty, are in OUT/metrics.jsonl)."""
    from detmatch.checkpoints import list_checkpoints

    lines = [f"trained {out} to step {step}"]
    scores = [f"{name} {metrics[key]['mAP']:.2f}" for key, name in
              (("3d", "3D"), ("bev", "BEV"), ("2d", "2D")) if key in metrics]  # fmt: skip
    if scores:
        lines.append(f"mAP (moderate, R40) on '{split}': {', '.join(scores)}")
    checkpoints = list_checkpoints(out)
    if checkpoints:
        lines.append(f"checkpoint: {checkpoints[-1]}")
    lines.append(f"metrics: {out / 'metrics.jsonl'}")
    return "\n".join(lines)


def predict(args: argparse.Namespace) -> int:
    from detmatch.inference import predict_split

    prepare_output(Path(args.out), args.overwrite, ("3d", "2d"))
    count = predict_split(
        Path(args.checkpoint), Path(args.data), frame_selection(args), Path(args.out)
    )
    print(f"wrote predictions for {count} frames to {args.out}/3d and {args.out}/2d")
    return 0


def add_parsers(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser("train", help="train the 2D and 3D detectors")
    parser.add_argument(
        "--config",
        required=True,
        help=f"TOML config file, or a packaged config's name: {', '.join(packaged_configs())}",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override any config key, e.g. train.steps=100, data.image_size=[320,96], "
        "ssl.tau_hung=-2 (repeatable; values are TOML literals, bare words are strings; "
        "--preset, --data, --steps, --method and --pretrained apply after them)",
    )
    parser.add_argument("--data", help="data set root; overrides [data] root")
    parser.add_argument(
        "--out",
        required=True,
        help="run directory: checkpoints, metrics.jsonl; must be new or empty unless --resume",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its latest checkpoint (a new run if it has none)",
    )
    parser.add_argument(
        "--steps",
        type=int,
        help="override the run's steps ([train] steps; a teacher-student method's [ssl] steps)",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        help="override [ssl] method: labeled-only (pre-training, [train]'s schedule), "
        "labeled-only-control (the pre-trained model continued with an EMA teacher, no "
        "unlabeled data), confidence thresholding or DetMatch; the teacher-student methods "
        "train [ssl] steps at [ssl] lr_2d / lr_3d, constant after [ssl] warmup_steps",
    )
    parser.add_argument("--pretrained", help="override [ssl] pretrained: the labeled-only run")
    parser.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        help="named DetMatch settings, applied after --set (paper: the paper's constants and "
        "loss as published; the defaults are what won on dev, BENCHMARKS.md)",
    )
    add_device_option(parser)
    parser.set_defaults(handler=train)

    parser = commands.add_parser("predict", help="write KITTI result files of both detectors")
    parser.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    parser.add_argument("--data", required=True, help="KITTI-layout data set root")
    add_frame_selection(parser)
    parser.add_argument("--out", required=True, help="output directory (gets 3d/ and 2d/)")
    add_overwrite_option(parser)
    parser.set_defaults(handler=predict)
