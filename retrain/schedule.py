"""Retraining on a schedule: `detmatch retrain ... --every 24h` runs rounds in the foreground
(a container's or a systemd service's main process), one per period, skipping a period when the
label store holds nothing new.

One scheduler per model repository: a scheduler (or a one-off `detmatch retrain`) holds an
exclusive lock on REPOSITORY/.retrain.lock (`filelock`: an flock, released by the kernel when
the process exits however it exits) for as long as it runs, and another one refuses to start,
naming the holder. Under torchrun, rank 0 holds it.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from filelock import FileLock, Timeout

from detmatch.files import atomic_write_bytes
from detmatch.training.distributed import DistributedContext
from retrain.round import RoundOutcome, RoundRequest, log_stderr, main_only, run_round

LOCK_FILE = ".retrain.lock"
HOLDER_FILE = ".retrain.holder.json"
UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


class LockHeld(RuntimeError):
    """Another scheduler (or round) holds the repository's retraining lock."""


def parse_period(text: str) -> float:
    """'90s', '15m', '24h', '7d', '1.5h' or plain seconds ('3600') -> seconds (> 0)."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([smhd]?)\s*", str(text))
    if not match or float(match.group(1)) <= 0:
        raise ValueError(f"--every {text!r}: expected a period such as 90s, 15m, 24h or 7d (> 0)")
    return float(match.group(1)) * UNITS[match.group(2) or "s"]


@contextlib.contextmanager
def retrain_lock(repository: Path) -> Iterator[None]:
    """Hold the repository's retraining lock, or raise LockHeld naming its holder."""
    if not repository.is_dir():
        raise FileNotFoundError(f"no model repository at {repository}")
    lock = FileLock(repository / LOCK_FILE, timeout=0)
    try:
        lock.acquire()
    except Timeout:
        holder = "unknown"
        with contextlib.suppress(OSError, ValueError):
            record = json.loads((repository / HOLDER_FILE).read_text())
            holder = f"pid {record['pid']} on {record['host']} since {record['since']}"
        raise LockHeld(
            f"another retraining holds {repository / LOCK_FILE} ({holder}); one scheduler "
            "retrains a repository at a time"
        ) from None
    try:
        record = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "since": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        atomic_write_bytes(repository / HOLDER_FILE, (json.dumps(record) + "\n").encode())
        yield
    finally:
        lock.release()


def run_scheduled(
    request: RoundRequest,
    context: DistributedContext,
    every_s: float | None = None,
    times: int | None = None,
    report: Callable[[RoundOutcome], None] = lambda outcome: None,
    log: Callable[[str], None] = log_stderr,
    sleep: Callable[[float], None] = time.sleep,
) -> list[RoundOutcome]:
    """One round (every_s None), or a round every every_s seconds, `times` times (None:
    forever), under the repository's lock; report(outcome) after each. A period that a round
    overruns starts the next round at once."""
    outcomes = []
    with contextlib.ExitStack() as held:
        # Rank 0 takes the lock; a refusal reaches every process of a torchrun job.
        main_only(context, lambda: held.enter_context(retrain_lock(request.repository)))
        if every_s is not None and context.is_main:
            log(f"retraining {request.repository} every {every_s:g} s (holding its lock)")
        tick = 0
        while True:
            started = time.monotonic()
            outcome = run_round(request, context, log)
            outcomes.append(outcome)
            report(outcome)
            tick += 1
            if every_s is None or (times is not None and tick >= times):
                return outcomes
            elapsed = time.monotonic() - started
            wait = main_only(context, lambda elapsed=elapsed: max(0.0, every_s - elapsed))
            if context.is_main:
                log(f"next round in {wait:.0f} s")
            sleep(wait)
