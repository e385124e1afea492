"""A real Label Studio server for the review tests, and a `detmatch review backend` process.

Label Studio is a large install (Django), so it lives in its own environment: the tests use
$DETMATCH_LABEL_STUDIO (the `label-studio` executable; `.ci/run` installs it in a separate
virtual environment) or `label-studio` on PATH. Without it the live tests skip, unless
$DETMATCH_REQUIRE_LABEL_STUDIO is set (CI), where a missing server fails them.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.retrain.conftest import SPLITS

USER, PASSWORD = "reviewer@example.com", "review-pass-1234"
# The tiny round of the retraining tests: its splits, 2 steps, any candidate promoted.
ROUND_OVERRIDES = (*SPLITS, "--set", "retrain.steps=2", "--set", "retrain.max_map_drop=100")
TOKEN = "0123456789abcdef0123456789abcdef01234567"


def label_studio_executable() -> str:
    found = os.environ.get("DETMATCH_LABEL_STUDIO") or shutil.which("label-studio")
    if found and Path(found).exists():
        return found
    if os.environ.get("DETMATCH_REQUIRE_LABEL_STUDIO"):
        pytest.fail("DETMATCH_REQUIRE_LABEL_STUDIO is set but no label-studio executable was "
                    "found ($DETMATCH_LABEL_STUDIO or PATH)")  # fmt: skip
    pytest.skip("no Label Studio server: set $DETMATCH_LABEL_STUDIO (see .ci/run)")


def stop(process: subprocess.Popen, timeout_s: float) -> None:
    """SIGTERM, then SIGKILL after timeout_s."""
    process.terminate()
    try:
        process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class LabelStudio:
    """A running Label Studio, called with its legacy API token."""

    def __init__(self, url: str) -> None:
        self.url = url

    def call(self, method: str, path: str, body=None, timeout: float = 120.0):
        """The JSON answer (None if empty); AssertionError with the answer on an error status."""
        status, data = http_call(method, self.url + path, body, timeout,
                                 {"Authorization": f"Token {TOKEN}"})  # fmt: skip
        text = data.decode()
        if status >= 400:
            raise AssertionError(f"{method} {path}: HTTP {status}: {text[:2000]}")
        return json.loads(text) if text.strip() else None


@contextlib.contextmanager
def label_studio_server(directory: Path) -> Iterator[LabelStudio]:
    """Label Studio on a free local port, its data (SQLite) under directory, nothing written
    to the home directory, no calls out; local ML backends allowed."""
    executable = label_studio_executable()
    port = free_port()
    env = {k: v for k, v in os.environ.items()
           if k not in ("USERNAME", "PASSWORD", "PORT", "HOST")}  # fmt: skip
    env.update(
        LABEL_STUDIO_BASE_DATA_DIR=str(directory), LABEL_STUDIO_USERNAME=USER,
        LABEL_STUDIO_PASSWORD=PASSWORD, LABEL_STUDIO_USER_TOKEN=TOKEN, SENTRY_DSN="",
        LATEST_VERSION_CHECK="false", COLLECT_ANALYTICS="false", ML_BLOCK_LOCAL_IP="false",
        SSRF_PROTECTION_ENABLED="false",
    )  # fmt: skip
    log = open(directory / "label-studio.log", "w")  # noqa: SIM115
    process = subprocess.Popen(
        [executable, "start", "--no-browser", "--internal-host", "127.0.0.1", "--port",
         str(port), "--data-dir", str(directory), "--enable-legacy-api-token"],
        env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip
    server = LabelStudio(f"http://127.0.0.1:{port}")
    try:
        deadline = time.monotonic() + 240
        while True:
            if process.poll() is not None:
                raise AssertionError(
                    "Label Studio exited: " + (directory / "label-studio.log").read_text()[-3000:]
                )
            with contextlib.suppress(OSError, AssertionError):
                server.call("GET", "/api/projects", timeout=5)
                break
            if time.monotonic() > deadline:
                raise AssertionError("Label Studio did not answer within 240 s")
            time.sleep(1)
        yield server
    finally:
        stop(process, 30)
        log.close()


@contextlib.contextmanager
def file_server(directory: Path) -> Iterator[str]:
    """The files of directory over HTTP on a free local port (where task images live)."""

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), partial(Quiet, directory=str(directory)))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/"
    finally:
        httpd.shutdown()
        httpd.server_close()


@contextlib.contextmanager
def backend_process(*args: str) -> Iterator[tuple[str, list[str]]]:
    """`detmatch review backend --port 0 ARGS`; yields its URL once it listens, and the lines
    it prints (filled as it prints them)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "commands.main", "review", "backend", "--port", "0", *args],
        cwd=REPO, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )  # fmt: skip
    lines: list[str] = []
    try:
        for line in process.stdout:
            lines.append(line)
            match = re.search(r"listening on (http://\S+)", line)
            if match:
                break
        else:
            raise AssertionError("the backend did not start: " + "".join(lines)[-3000:])
        threading.Thread(target=lambda: [lines.append(x) for x in process.stdout],
                         daemon=True).start()  # fmt: skip
        yield match.group(1), lines
    finally:
        stop(process, 60)


def http_call(
    method: str, url: str, body=None, timeout: float = 120.0, headers: dict | None = None
) -> tuple[int, bytes]:
    """(status, body bytes) of an HTTP call, error statuses included; body: JSON-able, or bytes
    sent as they are."""
    data = body if body is None or isinstance(body, bytes) else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, method=method,
                                     headers={"Content-Type": "application/json",
                                              **(headers or {})})  # fmt: skip
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def http_json(method: str, url: str, body=None, timeout: float = 120.0) -> tuple[int, dict]:
    """(status, JSON body) of a call to the backend, error statuses included."""
    status, data = http_call(method, url, body, timeout)
    return status, json.loads(data or b"{}")


def wait_for_rounds(url: str, count: int, timeout_s: float = 600.0) -> list[dict]:
    """The backend's finished retraining rounds, once `count` have finished and none runs."""
    deadline = time.monotonic() + timeout_s
    while True:
        _, health = http_json("GET", url + "/health")
        training = health["training"]
        finished = [r for r in training["rounds"] if r["finished"] is not None]
        if len(finished) >= count and not training["running"] and not training["queued"]:
            return training["rounds"]
        if time.monotonic() > deadline:
            raise AssertionError(f"rounds after {timeout_s} s: {training}")
        time.sleep(0.5)
