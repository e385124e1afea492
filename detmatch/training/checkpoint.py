"""Writing checkpoints that hold everything needed to resume, atomically and durably; reading
them is `detmatch.checkpoints`'s."""

from __future__ import annotations

import io
import random
from pathlib import Path
from typing import Any

import torch

from detmatch.files import atomic_write_bytes


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Serialise, then write atomically and durably (temporary file, fsync, rename)."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(path, buffer.getvalue(), durable=True)


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
