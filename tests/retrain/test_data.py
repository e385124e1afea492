"""A round's frames: the original splits linked, every stored frame copied under a store- id,
gate frames sent to the service left out, stored labels as fixed targets when configured."""

from __future__ import annotations

import pytest

from commands.main import main
from detmatch.data.kitti import KittiDataset, read_image_set, read_objects
from retrain.data import (
    GATE_SPLIT,
    LABELED_SPLIT,
    UNLABELED_SPLIT,
    SourceSplits,
    compose_round_data,
    stored_frame_id,
)
from retrain.snapshot import store_snapshot
from serving.store import DEFAULT_NAMESPACE
from serving.store_index import SharedStore, store_files_root
from serving.store_layout import frame_paths
from tests.conftest import KITTI_SAMPLE
from tests.postgres import postgres_server, postgres_url  # noqa: F401 - fixtures

SOURCES = SourceSplits("labeled", "unlabeled", "val")


def _stored(repository, data, store, *args: str) -> None:
    where = ["--store", str(store)]
    if isinstance(store, SharedStore):
        where = ["--store", store.url, "--store-root", str(store.root)]
    assert main(["label", "--repository", str(repository), "--data", str(data), *where,
                 "--tau-hung", "50", *args]) == 0  # fmt: skip


@pytest.fixture(params=["embedded", "shared"])
def any_store(request, tmp_path):
    """A store's directory, or a shared store (PostgreSQL index) whose files are there."""
    if request.param == "embedded":
        return tmp_path / "store"
    return SharedStore(request.getfixturevalue("postgres_url"), tmp_path / "store")


@pytest.mark.parametrize("stored_labels", ["pool", "labeled"])
def test_round_data_gathers_every_shard_and_keeps_the_gate_out(
    tmp_path, repository, round_data, stored_labels, any_store
):
    store = any_store
    files = store_files_root(store)
    gate = read_image_set(round_data / "ImageSets" / "val.txt")
    # Shard a: real KITTI frames (ids other than the gate frame's: this store keys bare ids);
    # shard b: a gate frame sent to the store.
    kitti = [i for i in ("000000", "000001", "000002") if i != gate[0]]
    (tmp_path / "kitti.txt").write_text("".join(f"{i}\n" for i in kitti))
    (tmp_path / "gate.txt").write_text(gate[0] + "\n")
    _stored(repository, KITTI_SAMPLE, store, "--ids-file", str(tmp_path / "kitti.txt"),
            "--shard", "a")  # fmt: skip
    _stored(repository, round_data, store, "--ids-file", str(tmp_path / "gate.txt"),
            "--shard", "b")  # fmt: skip

    out = tmp_path / "round"
    data = compose_round_data(round_data, store, out, SOURCES, stored_labels, progress=False)
    counts = (data.labeled, data.unlabeled, data.stored, data.excluded, data.gate)
    assert counts == (2, 2, len(kitti), 1, 2)
    assert data.store_snapshot == store_snapshot(store).id  # everything read, gate frame too
    stored = [stored_frame_id(i) for i in kitti]
    labeled = read_image_set(out / "ImageSets" / f"{LABELED_SPLIT}.txt")
    unlabeled = read_image_set(out / "ImageSets" / f"{UNLABELED_SPLIT}.txt")
    original = read_image_set(round_data / "ImageSets" / "labeled.txt")
    pool = read_image_set(round_data / "ImageSets" / "unlabeled.txt")
    if stored_labels == "pool":
        assert labeled == original and unlabeled == pool + stored
    else:
        assert labeled == original + stored and unlabeled == pool
    assert read_image_set(out / "ImageSets" / f"{GATE_SPLIT}.txt") == gate
    dataset = KittiDataset(out)
    dataset.check_frames(labeled + unlabeled + gate)
    kept = files / "shards" / "a" / frame_paths(DEFAULT_NAMESPACE, kitti[0])["label_2"]
    assert dataset.label_path(stored[0]).read_text() == kept.read_text()  # the stored labels
    assert len(read_objects(kept)) > 0
    assert dataset.points_path(gate[0]).is_symlink()  # the original frames are linked
    assert not (out / ".store_export").exists()


def test_stored_ids_never_collide_with_the_data_set():
    assert stored_frame_id("000001") == "store-000001"
    long = "x" * 64
    assert stored_frame_id(long).startswith("store-") and len(stored_frame_id(long)) <= 64
    assert stored_frame_id(long) != stored_frame_id("y" * 64)
