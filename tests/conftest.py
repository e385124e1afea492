from pathlib import Path

import pytest

# Three real KITTI frames (shared fixtures beside the repository, see ../shared/kitti_sample).
KITTI_SAMPLE = Path(__file__).resolve().parents[1].parent / "shared" / "kitti_sample"


@pytest.fixture(scope="session")
def kitti_sample() -> Path:
    if not (KITTI_SAMPLE / "training").is_dir():
        raise FileNotFoundError(f"the KITTI sample frames are missing at {KITTI_SAMPLE}")
    return KITTI_SAMPLE
