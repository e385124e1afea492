"""What every command group shares: the help formatter, --version, --device, which frames of a
data set to read, and the refusal to write a run into an existing one."""

from __future__ import annotations

import argparse
import shutil
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from detmatch.config import DEVICES
from detmatch.data.kitti import SUBSETS
from detmatch.data.selection import FrameSelection


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's default in --help, except where there is none (None, False, "", []) or
    the help text already states it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        help_text = action.help or ""
        default = action.default
        if (
            default is None
            or default is False
            or default is argparse.SUPPRESS
            or (isinstance(default, str | list) and not default)
            or "default" in help_text
        ):
            return help_text
        return super()._get_help_string(action)


def package_version() -> str:
    """The installed distribution's version (the source tree's when not installed)."""
    try:
        return version("detmatch")
    except PackageNotFoundError:
        from detmatch import __version__

        return __version__


def show_defaults(parser: argparse.ArgumentParser) -> None:
    """HelpFormatter for the parser and all its subcommands, however deeply nested."""
    parser.formatter_class = HelpFormatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                show_defaults(subparser)


def add_version_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--version", action="version", version=f"{parser.prog} {package_version()}")


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """--device of the commands that train."""
    parser.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where to train: auto (a CUDA GPU when there is one), cpu or cuda",
    )


def add_frame_selection(parser: argparse.ArgumentParser) -> None:
    """--split | --ids-file | --all, and --subset: which frames of --data to read."""
    frames = parser.add_mutually_exclusive_group(required=True)
    frames.add_argument("--split", help="ImageSets split: the ids in DATA/ImageSets/SPLIT.txt")
    frames.add_argument("--ids-file", help="a file of frame ids, one a line (no ImageSets needed)")
    frames.add_argument(
        "--all", action="store_true", help="every frame with an image (PNG or JPEG) in image_2/"
    )
    parser.add_argument(
        "--subset",
        choices=SUBSETS,
        help="DATA's subset directory to read (default: training/ if DATA has one, else testing/)",
    )


def frame_selection(args: argparse.Namespace) -> FrameSelection:
    """The frames chosen by the options `add_frame_selection` added."""
    ids_file = Path(args.ids_file) if args.ids_file else None
    return FrameSelection(args.split, ids_file, args.all, args.subset)


def _holds_files(out: Path) -> bool:
    """Whether --out exists and is not empty; FileExistsError when it is not a directory."""
    if not out.exists():
        return False
    if not out.is_dir():
        raise FileExistsError(f"--out {out} exists and is not a directory")
    return any(out.iterdir())


def refuse_existing_run(out: Path, resume: bool) -> None:
    """A run directory that exists and is not empty is another run: training into it would
    append to its metrics.jsonl and overwrite its checkpoints. Only --resume may continue it."""
    if not resume and _holds_files(out):
        raise FileExistsError(
            f"--out {out} already holds a run (it is not empty): pass --resume to continue it, "
            "or choose a new run directory"
        )


def add_overwrite_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="write into a non-empty --out, first removing what this command writes there",
    )


def prepare_output(out: Path, overwrite: bool, written: Sequence[str]) -> None:
    """An output directory that exists and holds files is an earlier result: writing into it
    would mix old and new files (stale frames or result files that a later step reads as
    current). Refused unless `overwrite`; with it, the entries this command writes there
    (`written`, names relative to out) are removed first, and nothing else is touched."""
    if not _holds_files(out):
        return
    if not overwrite:
        raise FileExistsError(
            f"--out {out} is not empty: pass --overwrite to replace what it holds, or choose "
            "a new directory"
        )
    for name in written:
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def class_names(text: str) -> list[str]:
    """A --classes value ("Car, Pedestrian,Cyclist") -> its names, blanks dropped."""
    return [name.strip() for name in text.split(",") if name.strip()]


def add_store_options(parser: argparse.ArgumentParser, required: bool, what: str) -> None:
    """--store (a directory, or a postgresql:// URL: the index every replica shares) and
    --store-root (the shared store's files)."""
    parser.add_argument(
        "--store", required=required,
        help=f"{what}: a directory (the embedded store: SQLite shard indexes), or a "
        "postgresql://USER:PASSWORD@HOST:PORT/DB URL (the index shared by every replica, "
        "with --store-root; the postgres extra); the password may come from $PGPASSWORD",
    )  # fmt: skip
    parser.add_argument(
        "--store-root",
        help="with a postgresql:// --store: the directory of the frames' files, mounted by "
        "every replica at the same path",
    )


def store_location(args: argparse.Namespace):
    """The store `--store` / `--store-root` name (serving.store_index.store_location)."""
    from serving.store_index import store_location as location

    return location(args.store, args.store_root)
