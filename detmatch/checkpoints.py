"""Finding and reading checkpoints (training writes them: `detmatch.training.checkpoint`).

Below the training code, so prediction, export and tools read checkpoints without importing
it. Loaded with weights_only=True (no arbitrary pickles), mapped to the CPU.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import torch

CHECKPOINT_PATTERN = re.compile(r"^step_(\d{8})\.pt$")


def checkpoint_dir(run_dir: Path) -> Path:
    return Path(run_dir) / "checkpoints"


def checkpoint_path(run_dir: Path, step: int) -> Path:
    return checkpoint_dir(run_dir) / f"step_{step:08d}.pt"


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Load a checkpoint file with weights_only=True, mapped to the CPU."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    return torch.load(path, map_location="cpu", weights_only=True)


def list_checkpoints(run_dir: Path) -> list[Path]:
    """A run's checkpoints, oldest step first."""
    directory = checkpoint_dir(run_dir)
    if not directory.is_dir():
        return []
    found = [p for p in directory.iterdir() if CHECKPOINT_PATTERN.match(p.name)]
    return sorted(found, key=lambda p: int(CHECKPOINT_PATTERN.match(p.name).group(1)))


def resolve_checkpoint(path: Path) -> Path:
    """A checkpoint file, or a run directory meaning its latest checkpoint."""
    path = Path(path)
    if path.is_file():
        return path
    if path.is_dir():
        found = list_checkpoints(path)
        if not found:
            raise FileNotFoundError(
                f"run directory {path} has no checkpoints in {checkpoint_dir(path)}"
            )
        return found[-1]
    raise FileNotFoundError(f"no checkpoint file or run directory at {path}")


def run_evaluations(run_dir: Path) -> dict[int, dict[str, Any]]:
    """The periodic evaluations a training run logged to its metrics.jsonl, by step."""
    evaluations = {}
    for line in (Path(run_dir) / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if "eval" in record:
            evaluations[record["step"]] = record["eval"]
    return evaluations
