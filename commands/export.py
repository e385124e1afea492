"""`detmatch-export`: a checkpoint -> a checked, published version of a model repository.

    detmatch-export --checkpoint CKPT --repository DIR [--version V] [--promote]
                    [--parity-data KITTI_DIR ...] [--no-checkpoint]
    detmatch-export --checkpoint CKPT --repository DIR --quantize int8 [--promote]
    detmatch-export --repository DIR --from-version V --quantize int8 [--calibration-data DIR]
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
    parser.add_argument(
        "--quantize",
        choices=["int8"],
        help="also publish an INT8 version (onnxruntime static quantization, QDQ, per-channel "
        "weights) of the exported one, or of --from-version; refused when its labels agree "
        "with the fp32 version's less than --min-agreement",
    )
    parser.add_argument("--from-version", metavar="VERSION",
                        help="with --quantize: quantize this published version")  # fmt: skip
    parser.add_argument(
        "--calibration-data",
        metavar="DIR",
        help="KITTI-layout frames to calibrate and check the INT8 version on (default: the "
        "training data the version's manifest names, if present)",
    )
    parser.add_argument("--calibration-frames", type=int, default=32,
                        help="frames the INT8 activations are calibrated on")  # fmt: skip
    parser.add_argument("--agreement-frames", type=int, default=32,
                        help="other frames both versions label to compare")  # fmt: skip
    parser.add_argument(
        "--min-agreement",
        type=float,
        default=0.95,
        help="share of the fp32 version's matched labels the INT8 version must reproduce "
        "(same class, 3D IoU >= 0.7, 2D IoU >= 0.7)",
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
            promote_version=args.promote is True and args.quantize is None,
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
    promote_int8 = args.quantize is not None and args.promote is True
    state = "published and promoted" if result.promoted else "published (not promoted)"
    print(f"{state} version {result.version}: {result.path}")
    if args.quantize is None:
        return 0
    return _quantize(args, result.version, promote_int8)


def _quantize(args: argparse.Namespace, source: str, promote_version: bool) -> int:
    from export.graphs import ExportCheckError
    from export.quantize import quantize_version
    from serving.repository import load_manifest, version_dir

    data = args.calibration_data
    if data is None:
        training = load_manifest(version_dir(args.repository, source)).training
        data = (training.config.get("data") or {}).get("root")
        if not data or not (Path(data) / "training" / "image_2").is_dir():
            raise ValueError(f"--quantize: version {source}'s training data ({data}) is not "
                             "here; give --calibration-data DIR")  # fmt: skip
    try:
        result = quantize_version(
            args.repository, source, data, args.calibration_frames, args.agreement_frames,
            args.min_agreement, promote_version=promote_version,
            log=None if args.quiet else lambda message: print(message, file=sys.stderr),
        )  # fmt: skip
    except ExportCheckError as error:
        print(f"detmatch-export: the INT8 version failed its check, nothing was published: "
              f"{error}", file=sys.stderr)  # fmt: skip
        return 1
    record = result.record
    state = "published and promoted" if result.promoted else "published (not promoted)"
    print(
        f"{state} INT8 version {result.version} of {source}: {result.path} ({record.reproduced}"
        f" of {record.matched_labels} matched labels reproduced, {record.agreement:.1%})"
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    repository = Path(args.repository)
    promote_existing = isinstance(args.promote, str)
    actions = [bool(args.checkpoint), args.list, promote_existing, bool(args.demote),
               bool(args.from_version)]  # fmt: skip
    if sum(actions) != 1:
        parser.error(
            "give exactly one of --checkpoint, --list, --promote VERSION, --demote VERSION, "
            "--from-version VERSION"
        )
    if args.from_version and args.quantize is None:
        parser.error("--from-version goes with --quantize int8")
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
        if args.from_version:
            return _quantize(args, args.from_version, args.promote is True)
        return _export(args)
    except (FileNotFoundError, ValueError) as error:
        print(f"detmatch-export: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
