"""What the review tests share: a label store holding the three KITTI sample frames labeled by
the tiny exported model (thresholds low enough that it labels), and one of them again under
namespace site-b; the retraining tests' model repository copy and tiny round data."""

from __future__ import annotations

import pytest

from serving.store import LabelStore
from tests.onnx_fixtures import exported_repository, served_labeler  # noqa: F401
from tests.retrain.conftest import repository, round_data  # noqa: F401
from tests.serving.store_helpers import put_frame

FRAMES = ("000000", "000001", "000002")


@pytest.fixture
def store(tmp_path, served_labeler):  # noqa: F811
    root = tmp_path / "store"
    with LabelStore(root, "a") as writer:
        for frame in FRAMES:
            put_frame(writer, served_labeler, frame, source=frame)
        put_frame(writer, served_labeler, "000000", source="000000", namespace="site-b")
    return root
