"""Model hot swap: watch the repository and serve the newest promoted version that loads.

Each check walks the promoted versions from the newest down: the first one that is served
already, or that loads, verifies (`verify_version`) and warms up beside the served one, is
served; a newer one that failed is skipped, so a new or restarted server falls back to the
newest promoted version that works and says so in its log. A version that failed is not
tried again until its directory changes (a fixed copy, a re-promotion). Versions never come
back from a failure silently: every failure and fallback is logged once, at ERROR, and a
repository without a promoted version is logged once with the command that promotes one.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path

from serving.labeler import Labeler
from serving.repository import PROMOTED_FILE, promoted_versions
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
        self.failed: dict[str, tuple] = {}  # version -> the directory's state when it failed
        self._said: str | None = None  # the last repository-level problem logged
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def check(self) -> bool:
        """Serve the newest promoted version that loads, if it is not served yet; True if a
        version was swapped in."""
        try:
            promoted = promoted_versions(self.root)
        except (OSError, ValueError) as error:
            self._say_once(f"cannot read model repository {self.root}: {error}")
            return False
        if not promoted:
            self._say_once(
                f"model repository {self.root} has no promoted version"
                + (f"; still serving {self.slot.version}" if self.slot.version else
                   ", so nothing is served (health NOT_SERVING)")
                + f"; promote one: detmatch-export --repository {self.root} --promote VERSION"
            )  # fmt: skip
            return False
        skipped = []
        for version in reversed(promoted):
            if version == self.slot.version:
                self._fell_back(version, skipped, swapped=False)
                return False
            state = self._state(version)
            if self.failed.get(version) == state:
                skipped.append(version)
                continue
            if self._try(version, state):
                self._fell_back(version, skipped, swapped=True)
                return True
            skipped.append(version)
        self._say_once(
            f"no promoted version of {self.root} loads ({', '.join(skipped)} failed); "
            + (f"still serving {self.slot.version}" if self.slot.version else "nothing is served")
        )
        return False

    def _try(self, version: str, state: tuple) -> bool:
        log.info("loading model version %s", version, extra={"fields": {"version": version}})
        try:
            labeler = self.load(self.root / version)
            labeler.warm_up()
        except Exception as error:  # noqa: BLE001 - any load failure keeps the old model
            self.failed[version] = state
            log.error(
                "loading model version %s failed, still serving %s: %s",
                version,
                self.slot.version,
                error,
                extra={"fields": {"version": version, "served": self.slot.version}},
            )
            return False
        old = self.slot.swap(labeler)
        self.failed.pop(version, None)
        self._said = None
        previous = old.version if old is not None else None
        log.info(
            "serving model version %s%s",
            version,
            f" (was {previous})" if previous else "",
            extra={"fields": {"version": version, "previous": previous}},
        )
        return True

    def _fell_back(self, version: str, skipped: list[str], swapped: bool) -> None:
        if not skipped:
            if self._said is not None and not swapped:
                self._said = None
            return
        self._say_once(
            f"serving model version {version}, not the newest promoted "
            f"{skipped[0]}: {', '.join(skipped)} failed to load (see the error above); "
            f"fix or demote it: detmatch-export --repository {self.root} --demote {skipped[0]}"
        )

    def _state(self, version: str) -> tuple:
        """What a retry waits for: a change of the version's files or of its promotion."""
        directory = self.root / version
        stats = []
        for path in sorted(directory.iterdir()) if directory.is_dir() else ():
            try:
                stat = path.stat()
            except FileNotFoundError:
                continue
            stats.append((path.name, stat.st_size, stat.st_mtime_ns))
        marker = directory / PROMOTED_FILE
        return tuple(stats), marker.stat().st_mtime_ns if marker.exists() else None

    def _say_once(self, message: str) -> None:
        if message != self._said:
            self._said = message
            log.error(message, extra={"fields": {"repository": str(self.root)}})

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
