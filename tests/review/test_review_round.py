"""Human-reviewed frames in a retraining round: a 3D review makes its frame a labeled frame
with the reviewer's labels (or a gate frame, by [retrain] reviewed_gate_fraction), a 2D-only
review leaves it in the pool, and a review is new data to the store's snapshot."""

from __future__ import annotations

import os
import shutil

import pytest

if os.environ.get("DETMATCH_REQUIRE_REVIEW"):  # .ci/run installs the review extra
    import datumaro  # noqa: F401
else:
    pytest.importorskip("datumaro", reason="the review extra: pip install -e '.[review]'")

from detmatch.data.kitti import KittiDataset, read_image_set, read_objects  # noqa: E402
from retrain.data import (  # noqa: E402
    GATE_SPLIT,
    LABELED_SPLIT,
    UNLABELED_SPLIT,
    SourceSplits,
    compose_round_data,
    stored_frame_id,
)
from retrain.report import data_table  # noqa: E402
from retrain.snapshot import store_snapshot  # noqa: E402
from serving.review import export_review, select_frames  # noqa: E402
from serving.reviews import import_review, read_human_labels  # noqa: E402
from tests.review.test_review_import import _label_studio_export  # noqa: E402

SOURCES = SourceSplits("labeled", "unlabeled", "val")


def _review_in_cvat(store, tmp_path, frame_id):
    """One stored frame reviewed in CVAT as exported (the reviewer accepted its labels)."""
    out = tmp_path / "cvat"
    shutil.rmtree(out, ignore_errors=True)
    chosen = [s for s in select_frames(store, namespace="default") if s.record.frame_id == frame_id]
    export_review(store, out, "cvat-3d", chosen)
    import_review(store, out, "cvat-3d")


@pytest.mark.parametrize("gate_fraction", [0.0, 0.999])
def test_a_3d_review_makes_a_labeled_frame(store, tmp_path, round_data, gate_fraction):
    before = store_snapshot(store)
    _review_in_cvat(store, tmp_path, "000001")
    after = store_snapshot(store)
    assert after.frames == before.frames and after.id != before.id  # a review is new data
    data = compose_round_data(round_data, store, tmp_path / "round", SOURCES,
                              progress=False, reviewed_gate_fraction=gate_fraction)  # fmt: skip
    assert data.store_snapshot == after.id
    reviewed = stored_frame_id("default__000001")
    splits = {name: read_image_set(tmp_path / "round" / "ImageSets" / f"{name}.txt")
              for name in (LABELED_SPLIT, UNLABELED_SPLIT, GATE_SPLIT)}  # fmt: skip
    assert data.reviewed == 1 and data.stored == 3  # 4 stored frames, one reviewed
    if gate_fraction:
        assert reviewed in splits[GATE_SPLIT] and data.reviewed_gate == 1
    else:
        assert reviewed in splits[LABELED_SPLIT] and data.reviewed_gate == 0
    assert reviewed not in splits[UNLABELED_SPLIT]
    rows = read_objects(KittiDataset(tmp_path / "round").label_path(reviewed))
    human = read_human_labels(store)[("default", "000001")]["labels"]
    assert rows.score is None and 0 < len(rows) <= len(human)  # the camera's view only
    assert set(rows.names) <= {label["class"] for label in human}
    assert "| human-reviewed stored frames" in data_table(data)


def test_a_2d_review_leaves_its_frame_in_the_pool(store, tmp_path, round_data):
    import json

    tasks = _label_studio_export(store, tmp_path)
    path = tmp_path / "ls.json"
    path.write_text(json.dumps(tasks))
    import_review(store, path, "label-studio")
    data = compose_round_data(round_data, store, tmp_path / "round", SOURCES, progress=False)
    assert data.reviewed == 0 and data.stored == 4
    assert data.store_snapshot == store_snapshot(store).id
