"""A real PostgreSQL server for the shared label store's tests.

`.ci/run` starts one (`.ci/postgres start`) and exports its URL as DETMATCH_TEST_POSTGRES;
without it the fixture starts its own the same way, where the machine has PostgreSQL's
binaries. Tests that need it skip only when neither is possible, and never under
DETMATCH_REQUIRE_SERVERS=1 (what `.ci/run` sets): there a missing server fails them.
Every test gets a database of its own."""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
URL_ENV = "DETMATCH_TEST_POSTGRES"
REQUIRE_ENV = "DETMATCH_REQUIRE_SERVERS"


def _unavailable(reason: str) -> None:
    if os.environ.get(REQUIRE_ENV):
        pytest.fail(f"{reason} (and {REQUIRE_ENV} is set)")
    pytest.skip(reason)


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[str]:
    """The URL of a PostgreSQL server's `detmatch` database (a role that may create
    databases)."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        _unavailable("psycopg is not installed (pip install -e '.[postgres]')")
    url = os.environ.get(URL_ENV)
    if url:
        yield url
        return
    # not under pytest's base directory: the server runs as the postgres user, who may not
    # enter root's 0700 temporary directories
    directory = Path(tempfile.mkdtemp(prefix="detmatch-postgres-"))
    directory.chmod(0o755)
    started = subprocess.run(
        [str(REPO / ".ci" / "postgres"), "start", str(directory)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    if started.returncode != 0:
        _unavailable(f"cannot start PostgreSQL: {started.stderr.strip()[-500:]}")
    try:
        yield started.stdout.strip()
    finally:
        subprocess.run([str(REPO / ".ci" / "postgres"), "stop", str(directory)], timeout=60)
        shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture
def postgres_url(postgres_server) -> Iterator[str]:
    """A fresh database on the server, dropped afterwards."""
    import psycopg

    name = f"t_{secrets.token_hex(6)}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        admin.execute(f"CREATE DATABASE {name}")
    base, _, _ = postgres_server.rpartition("/")
    yield f"{base}/{name}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        admin.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
