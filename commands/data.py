"""Data sets: `detmatch synth`, `split` and `show`."""

from __future__ import annotations

import argparse
from pathlib import Path

from commands.common import add_overwrite_option, prepare_output
from detmatch.data.kitti import SUBSETS
from detmatch.data.synth.world import DEFAULT_WORLD, WORLDS

# What `detmatch synth` writes into --out (removed first by --overwrite).
SYNTH_OUTPUTS = ("training", "ImageSets", "synth.json")


def synth(args: argparse.Namespace) -> int:
    from detmatch.data.synth import generate_dataset

    prepare_output(Path(args.out), args.overwrite, SYNTH_OUTPUTS)
    generate_dataset(
        out_dir=Path(args.out),
        num_frames=args.frames,
        seed=args.seed,
        resolution=args.resolution,
        workers=args.workers,
        val_fraction=args.val_fraction,
        progress=not args.quiet,
        world=args.world,
    )
    print(f"wrote {args.frames} frames of world {args.world} to {args.out}")
    return 0


def split(args: argparse.Namespace) -> int:
    from detmatch.data.splits import make_split

    result = make_split(
        Path(args.data), args.fraction, args.seed, args.source, dev_fraction=args.dev_fraction
    )
    if result.dev_path is not None:
        print(f"dev:       {result.num_dev:6d} frames -> {result.dev_path}")
    print(
        f"labeled:   {result.num_labeled:6d} frames -> {result.labeled_path}\n"
        f"unlabeled: {result.num_unlabeled:6d} frames -> {result.unlabeled_path}"
    )
    return 0


def show(args: argparse.Namespace) -> int:
    from detmatch.data.kitti import KittiDataset, read_objects
    from detmatch.data.visualize import save_frame_picture

    dataset = KittiDataset(Path(args.data), args.subset)
    frame = dataset.load_frame(args.frame)
    predictions = None
    if args.predictions:
        predictions = read_objects(_result_file(Path(args.predictions), args.frame))
    save_frame_picture(frame, Path(args.out), predictions=predictions)
    print(f"wrote {args.out}")
    return 0


def _result_file(directory: Path, frame_id: str) -> Path:
    """DIR/ID.txt, or DIR/3d/ID.txt where DIR is what `detmatch predict` or `label` wrote."""
    if not directory.is_dir():
        raise FileNotFoundError(f"--predictions {directory} is not a directory")
    for candidate in (directory / f"{frame_id}.txt", directory / "3d" / f"{frame_id}.txt"):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"--predictions {directory} has no result file for frame {frame_id} ({frame_id}.txt, "
        f"or 3d/{frame_id}.txt as predict and label write it)"
    )


def add_parsers(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "synth", help="generate a synthetic paired camera + LiDAR data set"
    )
    parser.add_argument("--out", required=True, help="output directory (KITTI layout)")
    parser.add_argument("--frames", type=int, required=True, help="number of frames")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed, same bytes)")
    parser.add_argument("--resolution", choices=("full", "half"), default="half",
                        help="full = 1242x375 (KITTI), half = 621x188")  # fmt: skip
    parser.add_argument(
        "--world", choices=sorted(WORLDS), default=DEFAULT_WORLD,
        help="world version: how the sensors fail (v3: frozen as the world calibrated to "
        "KITTI's trade-off, people clearer to the camera than to the LiDAR; docs/data.md)",
    )  # fmt: skip
    parser.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    parser.add_argument("--val-fraction", type=float, default=0.25,
                        help="fraction of frames in ImageSets/val.txt")  # fmt: skip
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite_option(parser)
    parser.set_defaults(handler=synth)

    parser = commands.add_parser(
        "split", help="write a labeled / unlabeled split of the train frames"
    )
    parser.add_argument("--data", required=True, help="KITTI-layout data set root")
    parser.add_argument("--fraction", type=float, required=True, help="labeled fraction in (0, 1)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the labeled subset")
    parser.add_argument("--source", default="train", help="ImageSets split to divide")
    parser.add_argument(
        "--dev-fraction",
        type=float,
        default=0.0,
        help="first hold out this fraction of the source as a labeled dev split for tuning "
        "(the same frames for every seed); 0: no dev split",
    )
    parser.set_defaults(handler=split)

    parser = commands.add_parser(
        "show", help="render a frame: image with 2D boxes + bird's-eye view"
    )
    parser.add_argument("--data", required=True, help="KITTI-layout data set root")
    parser.add_argument("--subset", choices=SUBSETS, default="training",
                        help="DATA's subset directory")  # fmt: skip
    parser.add_argument("--frame", required=True, help="frame id, e.g. 000001")
    parser.add_argument("--out", required=True, help="output PNG")
    parser.add_argument(
        "--predictions",
        help="directory of KITTI result files to overlay (dashed): DIR/ID.txt, or "
        "DIR/3d/ID.txt as predict and label write them",
    )
    parser.set_defaults(handler=show)
