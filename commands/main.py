"""`detmatch`: the parser assembled from each command group's sub-commands, and the dispatch.

    python -m commands.main COMMAND ...   (what `torchrun -m commands.main train ...` runs)

Exit status: the command's, or 2 for bad arguments, missing or existing files and config
errors (the message names them, no traceback).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from commands import data, evaluate, labeling, retrain, review, store, train
from commands.common import add_version_option, show_defaults

# The order `detmatch --help` lists them in.
GROUPS = (data, train, labeling, retrain, store, review, evaluate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="detmatch", description="Joint 2D-3D semi-supervised detection (DetMatch)."
    )
    add_version_option(parser)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in GROUPS:
        group.add_parsers(commands)
    show_defaults(parser)
    return parser


# A user's mistakes: a missing, existing or unreadable file or folder, a bad value (configs,
# data files and arguments raise ValueError subclasses). One line naming it, exit status 2;
# anything else is a fault of ours and keeps its traceback.
USER_ERRORS = (
    FileNotFoundError,
    FileExistsError,
    IsADirectoryError,
    NotADirectoryError,
    PermissionError,
    ValueError,
)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    name = " ".join(filter(None, ("detmatch", args.command, getattr(args, "store_command", None))))
    try:
        return args.handler(args)
    except USER_ERRORS as error:
        print(f"{name}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
