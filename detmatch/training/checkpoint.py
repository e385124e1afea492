"""Checkpoints that hold everything needed to resume, written atomically, loaded with
weights_only=True (no arbitrary pickles)."""

from __future__ import annotations

import io
import random
import re
from pathlib import Path
from typing import Any

import torch

from detmatch.files import atomic_write_bytes

CHECKPOINT_PATTERN = re.compile(r"^step_(\d{8})\.pt$")


def checkpoint_dir(run_dir: Path) -> Path:
    return Path(run_dir) / "checkpoints"


def checkpoint_path(run_dir: Path, step: int) -> Path:
    return checkpoint_dir(run_dir) / f"step_{step:08d}.pt"


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Serialise, then write atomically and durably (temporary file, fsync, rename)."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(path, buffer.getvalue(), durable=True)


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


def rng_state() -> dict[str, Any]:
    """Global torch and Python RNG states as tensors and plain values (weights_only-safe).

    Data order and augmentation draw from generators seeded by (seed, stream position), not
    from global state, so these two are all a resumed run needs.
    """
    python_version, python_state, python_gauss = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "python": {
            "version": python_version,
            "state": torch.tensor(python_state, dtype=torch.int64),
            "gauss": python_gauss,
        },
    }


def restore_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    python_state = state["python"]
    random.setstate(
        (python_state["version"], tuple(python_state["state"].tolist()), python_state["gauss"])
    )
