"""Model hot swap: a newly promoted version is loaded beside the served one and swapped in
while requests run; a failed load keeps the served model."""

from __future__ import annotations

import logging
import shutil
import threading
import time

import grpc
from grpc_health.v1 import health_pb2

from serving.client import LabelingClient
from serving.labeler import Labeler
from serving.repository import demote, promote, promoted_versions
from serving.service import ModelSlot
from serving.watcher import RepositoryWatcher
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import add_version, copy_repository, running_server
from tests.grpc_service.test_server import check_health


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
        add_version(repository, "000002", corrupt=True)  # never serves
        deadline = time.monotonic() + 60
        while "000002" not in watcher.failed and time.monotonic() < deadline:
            time.sleep(0.01)
        add_version(repository, "000003")
        while slot.version != "000003" and time.monotonic() < deadline:
            time.sleep(0.01)
        swapped.set()
        for thread in threads:
            thread.join(timeout=120)
    watcher.stop()
    assert errors == []
    for sequence in versions.values():
        changes = sum(a != b for a, b in zip(sequence, sequence[1:], strict=False))
        assert sequence[0] == "000001" and sequence[-1] == "000003" and changes == 1


def test_failed_load_keeps_serving_the_old_model(tmp_path, exported_repository, caplog):
    repository = copy_repository(exported_repository, tmp_path / "models")
    slot = ModelSlot()
    watcher = RepositoryWatcher(repository, slot)
    assert watcher.check()
    add_version(repository, "000002", corrupt=True)
    with caplog.at_level(logging.ERROR, logger="detmatch.serving"):
        assert not watcher.check()
    assert "loading model version 000002 failed, still serving 000001" in caplog.text
    assert slot.version == "000001" and set(watcher.failed) == {"000002"}
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


def test_a_starting_server_falls_back_to_the_newest_promoted_version_that_loads(
    tmp_path, exported_repository, caplog
):
    """Defect 3: with a corrupt newest promoted version a new server stayed NOT_SERVING
    forever ("still serving None") although 000001 was valid."""
    repository = copy_repository(exported_repository, tmp_path / "models")
    add_version(repository, "000002", corrupt=True)
    slot = ModelSlot()
    watcher = RepositoryWatcher(repository, slot)
    with caplog.at_level(logging.INFO, logger="detmatch.serving"):
        assert watcher.check()
    assert slot.version == "000001"
    assert "serving model version 000001, not the newest promoted 000002" in caplog.text
    assert f"--repository {repository} --demote 000002" in caplog.text
    with running_server(slot, tmp_path / "store") as running:
        assert check_health(running.target) == health_pb2.HealthCheckResponse.SERVING
        with LabelingClient(running.target) as client:
            assert client.model_info().version == "000001"


def test_promote_refuses_a_version_that_fails_verification(tmp_path, exported_repository, capsys):
    from commands.export import main as export_main

    repository = copy_repository(exported_repository, tmp_path / "models")
    add_version(repository, "000002")
    demote(repository, "000002")
    model = repository / "000002" / "detector3d.onnx"
    model.write_bytes(model.read_bytes()[:100])
    assert export_main(["--repository", str(repository), "--promote", "2"]) == 2
    error = capsys.readouterr().err
    assert "refusing to promote 000002" in error and "does not match its checksum" in error
    assert promoted_versions(repository) == ["000001"]


def test_a_hand_copied_version_is_rejected_once(tmp_path, exported_repository, caplog):
    """Defect 10: a version folder copied by hand (its manifest names 000001) was loaded and
    swapped in again at every poll."""
    repository = copy_repository(exported_repository, tmp_path / "models")
    shutil.copytree(repository / "000001", repository / "000002")  # PROMOTED marker included
    loads = []

    def load(path):
        loads.append(path.name)
        return Labeler(path)

    slot = ModelSlot()
    watcher = RepositoryWatcher(repository, slot, load=load)
    with caplog.at_level(logging.ERROR, logger="detmatch.serving"):
        for _ in range(4):
            watcher.check()
    assert slot.version == "000001"
    assert loads == ["000002", "000001"]
    assert caplog.text.count("names version 000001, not 000002") == 1


def test_no_promoted_version_is_logged_once_with_the_command(tmp_path, exported_repository, caplog):
    repository = copy_repository(exported_repository, tmp_path / "models")
    demote(repository, "000001")
    slot = ModelSlot()
    watcher = RepositoryWatcher(repository, slot)
    with caplog.at_level(logging.WARNING, logger="detmatch.serving"):
        for _ in range(3):
            assert not watcher.check()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "has no promoted version" in lines[0]
    assert f"detmatch-export --repository {repository} --promote VERSION" in lines[0]
    promote(repository, "000001")
    assert watcher.check() and slot.version == "000001"
