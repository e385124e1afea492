"""Fixtures of the gRPC service tests: a served labeler of the tiny exported model, a running
in-process server on 127.0.0.1 port 0 (the asyncio server on a thread of its own), and
`detmatch serve` in a torch-free subprocess."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import pytest

from serving.batching import batcher_for
from serving.config import ServerConfig
from serving.health_check import wait_until_serving
from serving.repository import promote
from serving.service import LabelingService, ModelSlot
from serving.store import LabelStore
from serving.testing import BackgroundServer
from tests.conftest import KITTI_SAMPLE, REPO
from tests.onnx_fixtures import (  # noqa: F401
    _one_torch_thread,
    exported_repository,
    served_labeler,
    trained_checkpoint,
)


@dataclass
class Running:
    port: int
    service: LabelingService
    store_root: Path
    background: BackgroundServer

    @property
    def target(self) -> str:
        return f"127.0.0.1:{self.port}"


@contextlib.contextmanager
def running_server(
    slot: ModelSlot, store_root: Path, config: ServerConfig | None = None
) -> Iterator[Running]:
    store = LabelStore(store_root, "s0")
    config = config or ServerConfig()
    batcher = batcher_for(config.batching())
    service = LabelingService(slot, store, config.max_image_pixels, config.max_points, batcher)
    background = BackgroundServer(service, config)
    try:
        port = background.start()
    except BaseException:
        store.close()
        raise
    try:
        yield Running(port, service, store_root, background)
    finally:
        background.stop()
        if batcher is not None:
            batcher.close()
        store.close()


@pytest.fixture
def server(tmp_path, served_labeler) -> Iterator[Running]:  # noqa: F811
    slot = ModelSlot()
    slot.swap(served_labeler)
    with running_server(slot, tmp_path / "store") as running:
        yield running


def copy_repository(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    return target


def add_version(root: Path, version: str, corrupt: bool = False) -> None:
    """A copy of version 000001 as `version`, promoted (corrupt: its 3D graph truncated after
    the promotion, as a failing disk or a hand edit would)."""
    path = root / version
    shutil.copytree(root / "000001", path)
    (path / "PROMOTED").unlink(missing_ok=True)
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["version"] = version
    (path / "manifest.json").write_text(json.dumps(manifest))
    promote(root, version)
    if corrupt:
        model = path / manifest["models"]["detector3d"]["file"]
        model.write_bytes(model.read_bytes()[:100])


def prometheus_sample(text: str, name: str, **labels: str) -> float:
    """The value of one sample of a Prometheus text exposition (0 when absent)."""
    for line in text.splitlines():
        if not line.startswith(name + "{") and not line.startswith(name + " "):
            continue
        head, value = line.rsplit(" ", 1)
        found = dict(re.findall(r'(\w+)="([^"]*)"', head))
        if head.split("{")[0] == name and all(found.get(k) == v for k, v in labels.items()):
            return float(value)
    return 0.0


TORCH_FREE_SERVE = (
    "import sys; sys.modules['torch'] = None; "
    "from commands.main import main; sys.exit(main(['serve'] + sys.argv[1:]))"
)


@contextlib.contextmanager
def serve_process(
    repository: Path, store: Path, *args: str, env: dict[str, str] | None = None
) -> Iterator[tuple[subprocess.Popen, str]]:
    """`detmatch serve` in a subprocess that cannot import torch; yields (process, target).
    Without a token in env, the server runs with --no-auth."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO), **(env or {})}
    if "--no-auth" not in args and not env.get("DETMATCH_TOKEN"):
        args = ("--no-auth", *args)
    command = [sys.executable, "-c", TORCH_FREE_SERVE, "--repository", str(repository),
               "--store", str(store), "--port", "0", "--shard", "s0", *args]  # fmt: skip
    process = subprocess.Popen(
        command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        line = process.stdout.readline()
        if not line.startswith("listening on "):
            process.kill()
            raise RuntimeError(f"server did not start: {line!r} {process.stderr.read()[-3000:]}")
        target = line.split()[-1]
        status = wait_until_serving(target, wait_s=60, poll_s=0.05)
        if status != "SERVING":
            raise TimeoutError(f"{target} is {status}, not SERVING, after 60 s")
        yield process, target
    finally:
        if process.poll() is None:
            process.kill()
        process.wait(timeout=30)
        process.stdout.close()
        process.stderr.close()


def send_frames(target: str, name: str, acknowledged: list[str], stop) -> None:
    """Label the KITTI sample's frame 000000 as NAME_0000, NAME_0001, ... until `stop` is set
    or a call fails, appending each acknowledged id (the SIGKILL tests' load)."""
    from serving.client import LabelingClient

    with LabelingClient(target, timeout_s=30) as client:
        for i in range(1000):
            if stop.is_set():
                return
            frame_id = f"{name}_{i:04d}"
            try:
                client.label_kitti_frame(KITTI_SAMPLE, "000000", send_as=frame_id)
            except grpc.RpcError:
                return
            acknowledged.append(frame_id)
