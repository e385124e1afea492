"""The label store of `detmatch serve`: `detmatch store export` (no torch)."""

from __future__ import annotations

import argparse
from pathlib import Path

from commands.common import add_overwrite_option, add_store_options, prepare_output, store_location

# What `detmatch store export` writes into --out (removed first by --overwrite).
EXPORT_OUTPUTS = ("training", "ImageSets", "labels", "export.json")


def store_export(args: argparse.Namespace) -> int:
    from serving.store import export_store

    prepare_output(Path(args.out), args.overwrite, EXPORT_OUTPUTS)
    summary = export_store(
        store_location(args), Path(args.out), args.val_fraction, args.seed, args.namespace or None
    )
    print(
        f"exported {summary.frames} stored frames of namespace(s) {', '.join(summary.namespaces)}"
        f" to {args.out} (KITTI layout, labels in label_2): ImageSets/train.txt {summary.train},"
        f" val.txt {summary.val} frames"
    )
    return 0


def add_parsers(commands: argparse._SubParsersAction) -> None:
    store = commands.add_parser("store", help="the label store of `detmatch serve`")
    actions = store.add_subparsers(dest="store_command", required=True, metavar="ACTION")
    parser = actions.add_parser(
        "export",
        help="a KITTI-layout data set of the stored frames and their labels, with train and "
        "val ImageSets (`detmatch train --data OUT` runs on it)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    add_store_options(parser, True, "label store")
    parser.add_argument("--out", required=True, help="output directory (KITTI layout)")
    parser.add_argument(
        "--val-fraction",
        type=float,
        default=0.1,
        help="share of frames held out in ImageSets/val.txt, chosen by a hash of each key (a "
        "frame keeps its side as the store grows)",
    )
    parser.add_argument("--seed", type=int, default=0, help="salt of that hash")
    parser.add_argument(
        "--namespace",
        action="append",
        help="export only this namespace (repeatable); frame ids stay bare when one namespace "
        "is exported, else NAMESPACE__ID",
    )
    add_overwrite_option(parser)
    parser.set_defaults(handler=store_export)
