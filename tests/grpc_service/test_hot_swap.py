"""Model hot swap: a newly promoted version is loaded beside the served one and swapped in
while requests run; a failed load keeps the served model."""

from __future__ import annotations

import logging
import threading
import time

import grpc

from serving.client import LabelingClient
from serving.labeler import Labeler
from serving.service import ModelSlot
from serving.watcher import RepositoryWatcher
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import add_version, copy_repository, running_server


def test_hot_swap_while_requests_run(tmp_path, exported_repository):
    repository = copy_repository(exported_repository, tmp_path / "models")
    slot = ModelSlot()
    watcher = RepositoryWatcher(repository, slot, poll_s=0.05)
    assert watcher.check() and slot.version == "000001"
    watcher.start()
    versions: dict[int, list[str]] = {0: [], 1: []}
    errors: list[grpc.RpcError] = []
    swapped = threading.Event()
    with running_server(slot, tmp_path / "store") as running:

        def send(worker: int) -> None:
            with LabelingClient(running.target) as client:
                after_swap = 0
                while after_swap < 5:
                    try:
                        response = client.label_kitti_frame(KITTI_SAMPLE, "000000", store=False)
                    except grpc.RpcError as error:
                        errors.append(error)
                        return
                    versions[worker].append(response.model_version)
                    after_swap += swapped.is_set()

        threads = [threading.Thread(target=send, args=(w,)) for w in versions]
        for thread in threads:
            thread.start()
        deadline = time.monotonic() + 60
        while min(len(v) for v in versions.values()) < 3 and not errors:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        add_version(repository, "000002")
        deadline = time.monotonic() + 60
        while slot.version != "000002" and time.monotonic() < deadline:
            time.sleep(0.01)
        swapped.set()
        for thread in threads:
            thread.join(timeout=120)
    watcher.stop()
    assert errors == []
    for sequence in versions.values():
        changes = sum(a != b for a, b in zip(sequence, sequence[1:], strict=False))
        assert sequence[0] == "000001" and sequence[-1] == "000002" and changes == 1


def test_failed_load_keeps_serving_the_old_model(tmp_path, exported_repository, caplog):
    repository = copy_repository(exported_repository, tmp_path / "models")
    slot = ModelSlot()
    watcher = RepositoryWatcher(repository, slot)
    assert watcher.check()
    add_version(repository, "000002", corrupt=True)
    with caplog.at_level(logging.ERROR, logger="detmatch.serving"):
        assert not watcher.check()
    assert "loading model version 000002 failed, still serving 000001" in caplog.text
    assert slot.version == "000001" and watcher.failed == "000002"
    assert not watcher.check()  # not retried until the served version changes
    with running_server(slot, tmp_path / "store") as running:
        with LabelingClient(running.target) as client:
            response = client.label_kitti_frame(KITTI_SAMPLE, "000000")
            assert response.model_version == "000001"
    add_version(repository, "000003")
    assert watcher.check() and slot.version == "000003"


def test_a_failed_warm_up_keeps_the_old_model(tmp_path, exported_repository):
    repository = copy_repository(exported_repository, tmp_path / "models")

    class BrokenWarmUp(Labeler):
        def warm_up(self, image_size=(1242, 375)) -> None:
            if self.version == "000002":
                raise RuntimeError("out of memory")

    slot = ModelSlot()
    watcher = RepositoryWatcher(repository, slot, load=BrokenWarmUp)
    assert watcher.check()
    add_version(repository, "000002")
    assert not watcher.check() and slot.version == "000001"
