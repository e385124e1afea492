"""Evaluation: `detmatch eval`, the KITTI object benchmark on result files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from commands.common import class_names


def evaluate(args: argparse.Namespace) -> int:
    from detmatch.data.kitti import read_image_set
    from detmatch.eval.kitti import evaluate_dirs, format_table

    if args.all:
        ids = sorted(path.stem for path in Path(args.gt_dir).glob("*.txt"))
        if not ids:
            raise FileNotFoundError(f"no label files (ID.txt) in {args.gt_dir}")
    else:
        ids = read_image_set(args.ids_file)
    results = evaluate_dirs(Path(args.gt_dir), Path(args.pred_dir), ids, class_names(args.classes))
    print(format_table(results))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


def add_parsers(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser("eval", help="KITTI object-benchmark evaluation")
    parser.add_argument("--gt-dir", required=True, help="directory of KITTI label files")
    parser.add_argument("--pred-dir", required=True, help="directory of KITTI result files")
    frames = parser.add_mutually_exclusive_group(required=True)
    frames.add_argument("--ids-file", help="ImageSets file of frame ids")
    frames.add_argument("--all", action="store_true",
                        help="every frame with a label file in --gt-dir")  # fmt: skip
    parser.add_argument("--classes", default="Car,Pedestrian,Cyclist", help="classes to score")
    parser.add_argument("--json", help="write the results as JSON here")
    parser.set_defaults(handler=evaluate)
