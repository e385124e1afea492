"""Two `detmatch serve` replicas on one shared label store (PostgreSQL index, one files root):
under load from both, SIGKILLs of either lose no acknowledged label and leave nothing a
row does not list; the same frame sent to both is stored once, with the re-labeling
policy's statuses; the store then feeds an export as one store."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

from serving.client import LabelingClient
from serving.store import check_integrity, export_store, list_frames
from serving.store_index import SharedStore
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import send_frames, serve_process
from tests.postgres import postgres_server, postgres_url  # noqa: F401 - fixtures

CREATED, REPLACED, UNCHANGED = 1, 3, 2  # serving.proto's StoreOutcome numbers


def _replica(repository, shared: SharedStore, shard: str):
    return serve_process(
        repository, shared.url, "--store-root", str(shared.root), "--shard", shard
    )  # fmt: skip


def test_replicas_killed_under_load_lose_no_acknowledged_label(
    tmp_path,
    exported_repository,
    postgres_url,  # noqa: F811
):
    shared = SharedStore(postgres_url, tmp_path / "root")
    acknowledged: list[str] = []
    for round_, victim in enumerate(("r1", "r2")):
        stop = threading.Event()
        with (
            _replica(exported_repository, shared, "r1") as (one, target_one),
            _replica(exported_repository, shared, "r2") as (two, target_two),
        ):
            targets = {"r1": target_one, "r2": target_two}
            processes = {"r1": one, "r2": two}
            threads = [
                threading.Thread(
                    target=send_frames, args=(targets[r], f"{round_}{r}w{w}", acknowledged, stop)
                )
                for r in targets
                for w in range(2)
            ]
            for thread in threads:
                thread.start()
            deadline = time.monotonic() + 120
            while len(acknowledged) < 8 * (round_ + 1) and time.monotonic() < deadline:
                time.sleep(0.01)
            processes[victim].send_signal(signal.SIGKILL)
            processes[victim].wait(timeout=30)
            time.sleep(0.3)  # the survivor keeps storing meanwhile
            stop.set()
            for thread in threads:
                thread.join(timeout=60)
        assert check_integrity(shared) == []
        stored = {r.frame_id for r in list_frames(shared)}
        assert set(acknowledged) <= stored
    assert {r.shard for r in list_frames(shared)} == {"r1", "r2"}

    # Reopened, each replica removes the debris of its kill: every file is one a row lists.
    with (
        _replica(exported_repository, shared, "r1") as (_, target_one),
        _replica(exported_repository, shared, "r2") as (_, target_two),
    ):
        assert _files(shared) == _listed(shared)
        with LabelingClient(target_one) as a, LabelingClient(target_two) as b:
            first = a.label_kitti_frame(KITTI_SAMPLE, "000001", send_as="both")
            second = b.label_kitti_frame(KITTI_SAMPLE, "000001", send_as="both")
            other = b.label_kitti_frame(KITTI_SAMPLE, "000002", send_as="both")
    assert (first.store_outcome, second.store_outcome, other.store_outcome) == (
        CREATED, UNCHANGED, REPLACED,
    )  # fmt: skip
    records = list_frames(shared)
    # (a frame stored just before a kill may not have been acknowledged: stored, all the same)
    assert {r.frame_id for r in records} == stored | {"both"}
    assert next(r for r in records if r.frame_id == "both").shard == "r2"
    # r2 took the key over; r1's superseded files stay until r1 opens its shard again
    superseded = _files(shared) - _listed(shared)
    assert {Path(p).parts[1] for p in superseded} == {"r1"} and len(superseded) == 5
    assert all(Path(p).stem == "both" for p in superseded)
    with _replica(exported_repository, shared, "r1"):
        pass
    assert _files(shared) == _listed(shared)
    summary = export_store(shared, tmp_path / "export")
    assert summary.frames == len(records)


def _listed(shared: SharedStore) -> set[str]:
    return {f"shards/{r.shard}/{relative}" for r in list_frames(shared) for relative in r.files}


def _files(shared: SharedStore) -> set[str]:
    return {
        p.relative_to(shared.root).as_posix()
        for p in (shared.root / "shards").rglob("*")
        if p.is_file() and p.name != ".lock"
    }
