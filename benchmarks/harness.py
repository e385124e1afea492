"""What every benchmark shares: its argument parser (the module's docstring is its help) and
the line that reruns it. Benchmarks run from the repository root as modules:

    python -m benchmarks.NAME [options]

and print their figures, then `rerun: python -m benchmarks.NAME ...` with the arguments they
were given (quoted for a POSIX shell)."""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence


def benchmark_parser(doc: str | None) -> argparse.ArgumentParser:
    """An argument parser whose --help is the benchmark's docstring, as written."""
    return argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )


def rerun(module: str, argv: Sequence[str] | None = None) -> str:
    """The command that runs benchmarks.<module> again with argv (default: this process's)."""
    args = list(sys.argv[1:] if argv is None else argv)
    return shlex.join(["python", "-m", f"benchmarks.{module}", *args])
