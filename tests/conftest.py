from pathlib import Path

import pytest

# Three real KITTI frames, shipped with their licence (tests/data/kitti/README.md).
KITTI_SAMPLE = Path(__file__).resolve().parent / "data" / "kitti"


@pytest.fixture(scope="session")
def kitti_sample() -> Path:
    if not (KITTI_SAMPLE / "training").is_dir():
        raise FileNotFoundError(f"the KITTI sample frames are missing at {KITTI_SAMPLE}")
    return KITTI_SAMPLE


REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def synth_root(tmp_path_factory) -> Path:
    """Six synthetic half-resolution frames (4 train, 2 val), generated once per session."""
    from detmatch.data.synth import generate_dataset

    root = tmp_path_factory.mktemp("synth")
    generate_dataset(
        out_dir=root, num_frames=6, seed=0, resolution="half", workers=1, val_fraction=0.34,
        progress=False,
    )  # fmt: skip
    return root
