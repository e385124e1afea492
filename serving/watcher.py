"""Model hot swap: watch the repository, load + warm up a newly promoted version beside the
served one, then swap it in. A failed load keeps the served model, is logged, and is not
retried until the served version of the repository changes again."""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path

from serving.labeler import Labeler
from serving.repository import served_version, version_dir
from serving.service import ModelSlot

log = logging.getLogger("detmatch.serving")


class RepositoryWatcher:
    def __init__(
        self,
        root: str | os.PathLike,
        slot: ModelSlot,
        poll_s: float = 2.0,
        load: Callable[[Path], Labeler] = Labeler,
    ) -> None:
        self.root = Path(root)
        self.slot = slot
        self.poll_s = poll_s
        self.load = load
        self.failed: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def check(self) -> bool:
        """Load and serve the repository's served version if it is new; True if swapped."""
        try:
            version = served_version(self.root)
        except (OSError, ValueError) as error:
            log.error("cannot read model repository %s: %s", self.root, error)
            return False
        if version is None or version == self.slot.version or version == self.failed:
            return False
        log.info("loading model version %s", version, extra={"fields": {"version": version}})
        try:
            labeler = self.load(version_dir(self.root, version))
            labeler.warm_up()
        except Exception as error:  # noqa: BLE001 - any load failure keeps the old model
            self.failed = version
            log.error(
                "loading model version %s failed, still serving %s: %s",
                version,
                self.slot.version,
                error,
            )
            return False
        old = self.slot.swap(labeler)
        self.failed = None
        log.info("serving model version %s (was %s)", version, old and old.version)
        return True

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="model-watcher", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            self.check()
