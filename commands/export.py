"""`detmatch-export`: a checkpoint -> a checked, published version of a model repository.

    detmatch-export --checkpoint CKPT --repository DIR [--version V] [--promote]
                    [--parity-data KITTI_DIR ...] [--no-checkpoint]
    detmatch-export --repository DIR --list
    detmatch-export --repository DIR --promote V | --demote V
    detmatch-export --version

Exit status: 0 published (or listed / promoted), 1 the export failed its checks (nothing was
published), 2 bad arguments or missing files.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from commands.common import package_version, show_defaults


class PublishVersionOrShow(argparse.Action):
    """`--version V` publishes as version V; `--version` alone prints the tool's version."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        if values is None:
            print(f"{parser.prog} {package_version()}")
            parser.exit()
        setattr(namespace, self.dest, values)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="detmatch-export",
        description="Export both detectors of a checkpoint to ONNX, check them against PyTorch "
        "and publish them as a new version of a model repository.",
    )
    parser.add_argument("--repository", required=True, help="model repository directory")
    parser.add_argument("--checkpoint", help="checkpoint file or run directory (its latest)")
    parser.add_argument(
        "--version",
        nargs="?",
        action=PublishVersionOrShow,
        metavar="V",
        help="version number to publish as (default: the next free one); without V: print "
        "detmatch-export's version and exit",
    )
    parser.add_argument(
        "--promote",
        nargs="?",
        const=True,
        default=None,
        metavar="VERSION",
        help="with --checkpoint: promote the new version once published; alone: promote an "
        "existing VERSION (the newest promoted version is the one served)",
    )
    parser.add_argument("--demote", metavar="VERSION", help="remove VERSION's promotion")
    parser.add_argument("--list", action="store_true", help="list versions and exit")
    parser.add_argument(
        "--parity-data",
        action="append",
        metavar="DIR",
        help="KITTI-layout directory whose frames the parity check also runs on (repeatable; "
        "default: the checkpoint's training data, if present); synthetic frames are always "
        "checked",
    )
    parser.add_argument(
        "--parity-frames",
        type=int,
        default=3,
        help="frames taken from each --parity-data directory",
    )
    parser.add_argument(
        "--synthetic-frames",
        type=int,
        default=2,
        help="rendered synthetic frames checked (alternately half and full KITTI resolution)",
    )
    parser.add_argument(
        "--no-checkpoint",
        action="store_true",
        help="do not copy the training checkpoint into the version (the manifest then only "
        "references it by path and SHA-256; `detmatch retrain` needs it there to continue)",
    )
    parser.add_argument("--rtol", type=float, default=1e-4, help="parity relative tolerance")
    parser.add_argument("--atol", type=float, default=1e-3, help="parity absolute tolerance")
    parser.add_argument("--quiet", action="store_true", help="print only the result")
    show_defaults(parser)
    return parser


def _list(repository: Path) -> int:
    from serving.repository import list_versions, load_manifest, promoted_versions, served_version

    promoted = set(promoted_versions(repository))
    served = served_version(repository)
    for version in list_versions(repository):
        manifest = load_manifest(repository / version)
        marks = ["promoted"] if version in promoted else []
        marks += ["served"] if version == served else []
        if manifest.retraining is not None:
            record = manifest.retraining
            gate = "passed" if record.passed else "failed"
            marks += [f"(round {record.round_id} from {record.parent_version}: gate {gate})"]
        step = manifest.training.step
        print(f"{version}  exported {manifest.exported_at}  step {step}  {' '.join(marks)}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from export.graphs import ExportCheckError
    from export.onnx_export import export_checkpoint
    from export.parity import Tolerance

    try:
        result = export_checkpoint(
            args.checkpoint,
            args.repository,
            version=args.version,
            promote_version=args.promote is True,
            parity_data=args.parity_data,
            parity_frames_per_source=args.parity_frames,
            synthetic_frames=args.synthetic_frames,
            tolerance=Tolerance(args.rtol, args.atol),
            log=None if args.quiet else lambda message: print(message, file=sys.stderr),
            keep_checkpoint=not args.no_checkpoint,
        )
    except ExportCheckError as error:
        print(f"detmatch-export: export failed, nothing was published: {error}", file=sys.stderr)
        return 1
    state = "published and promoted" if result.promoted else "published (not promoted)"
    print(f"{state} version {result.version}: {result.path}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    repository = Path(args.repository)
    promote_existing = isinstance(args.promote, str)
    actions = [bool(args.checkpoint), args.list, promote_existing, bool(args.demote)]
    if sum(actions) != 1:
        parser.error(
            "give exactly one of --checkpoint, --list, --promote VERSION, --demote VERSION"
        )
    try:
        if args.list:
            return _list(repository)
        if promote_existing or args.demote:
            from serving.repository import demote, promote, served_version

            name = (
                promote(repository, args.promote)
                if promote_existing
                else demote(repository, args.demote)
            )
            print(f"{'promoted' if promote_existing else 'demoted'} {name}; "
                  f"served version: {served_version(repository)}")  # fmt: skip
            return 0
        return _export(args)
    except (FileNotFoundError, ValueError) as error:
        print(f"detmatch-export: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
