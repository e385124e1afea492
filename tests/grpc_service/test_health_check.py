"""`detmatch health`, the container's HEALTHCHECK: asks a real server's gRPC health service
and exits 0 only when it is SERVING."""

import os
import socket
import subprocess
import sys
import threading

from commands.main import main
from serving.health_check import check_health
from serving.service import ModelSlot
from tests.conftest import REPO
from tests.grpc_service.conftest import running_server

# `detmatch health` in a process that cannot import torch (the serve image has none).
TORCH_FREE_HEALTH = (
    "import sys; sys.modules['torch'] = None; "
    "from commands.main import main; sys.exit(main(['health'] + sys.argv[1:]))"
)


def test_serving_server_is_healthy(server, capsys):
    assert check_health(server.target) == "SERVING"
    assert check_health(server.target, service="detmatch.v1.AutoLabeler") == "SERVING"
    assert check_health(server.target, service="no.such.Service") == "SERVICE_UNKNOWN"
    assert main(["health", "--target", server.target]) == 0
    assert capsys.readouterr().out.strip() == "SERVING"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    result = subprocess.run(
        [sys.executable, "-c", TORCH_FREE_HEALTH, "--target", server.target],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 0 and result.stdout.strip() == "SERVING", result.stderr


def test_a_server_without_a_model_is_unhealthy_until_one_is_served(
    tmp_path, served_labeler, capsys
):
    slot = ModelSlot()
    with running_server(slot, tmp_path / "store") as running:
        assert main(["health", "--target", running.target]) == 1
        assert capsys.readouterr().out.strip() == "NOT_SERVING"
        timer = threading.Timer(0.5, slot.swap, args=(served_labeler,))
        timer.start()
        try:
            assert main(["health", "--target", running.target, "--wait-s", "30"]) == 0
        finally:
            timer.join()
        assert capsys.readouterr().out.strip() == "SERVING"


def test_nothing_listening_is_unreachable(capsys):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    target = f"127.0.0.1:{port}"
    assert main(["health", "--target", target, "--timeout-s", "2"]) == 1
    assert capsys.readouterr().out.strip() == "UNREACHABLE"
