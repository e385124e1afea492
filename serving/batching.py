"""Dynamic batching: concurrent LabelFrame calls labeled together in one call of each graph.

Triton's dynamic batcher, with its names: a call's frame joins a queue; the batcher takes the
oldest frame and waits at most `max_queue_delay_us` microseconds for more, up to
`max_batch_size` frames in all, then labels them in one `Labeler.label_batch` (one 2D graph
call per image size, one 3D graph call) on its own thread, one batch at a time, and answers
every call with its own frame's labels. A frame with a malformed input or option fails its
own call only; so does any other error a batch raises, because the batcher then labels that
batch's frames one by one. Frames are batched only with frames of the same model version: a
swap never mixes two versions in one graph call.

Off by default (`max_batch_size` 1: each call labels its frame on its own inference thread):
on this project's 2-core CPU a batch makes no frame cheaper (BENCHMARKS.md, "Dynamic
batching"). Each frame waiting in a batch holds one of the server's inference threads, so a
batch can hold at most `workers` frames.
"""

from __future__ import annotations

import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field

from serving.labeler import Frame, FrameLabels, Labeler


@dataclass(frozen=True)
class BatchingSettings:
    """max_batch_size: frames labeled in one pair of graph calls (1: no batching);
    max_queue_delay_us: how long the oldest frame waits for others to join its batch."""

    max_batch_size: int = 1
    max_queue_delay_us: int = 2000

    def __post_init__(self) -> None:
        if self.max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {self.max_batch_size}")
        if self.max_queue_delay_us < 0:
            raise ValueError(f"max_queue_delay_us must be >= 0, got {self.max_queue_delay_us}")

    @property
    def enabled(self) -> bool:
        return self.max_batch_size > 1


@dataclass
class _Queued:
    labeler: Labeler
    frame: Frame
    future: Future = field(default_factory=Future)


@dataclass
class BatchStats:
    """batches: graph-call pairs run; frames: frames they labeled."""

    batches: int = 0
    frames: int = 0
    sizes: dict[int, int] = field(default_factory=dict)  # batch size -> batches of that size


def batcher_for(settings: BatchingSettings) -> Batcher | None:
    """The batcher the settings ask for; None when batching is off."""
    return Batcher(settings) if settings.enabled else None


class Batcher:
    """The queue and the thread that labels its batches. `label` blocks its caller until its
    frame's batch has run; `close` labels what is queued, then stops the thread."""

    def __init__(self, settings: BatchingSettings) -> None:
        if not settings.enabled:
            raise ValueError("a Batcher needs max_batch_size >= 2 (1 is no batching)")
        self.settings = settings
        self.stats = BatchStats()
        self._queue: queue.SimpleQueue[_Queued | None] = queue.SimpleQueue()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="batcher", daemon=True)
        self._thread.start()

    def label(self, labeler: Labeler, frame: Frame) -> FrameLabels:
        """The frame's labels, from its batch; raises its ValueError (a malformed input or
        option) or whatever labeling it alone raised."""
        if self._closed:
            raise RuntimeError("the batcher is closed")
        queued = _Queued(labeler, frame)
        self._queue.put(queued)
        return queued.future.result()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._thread.join()

    # --- the batcher's thread --------------------------------------------------------------------

    def _run(self) -> None:
        carried: _Queued | None = None  # a frame of another version, first of the next batch
        stopping = False
        while not stopping or carried is not None:
            first = carried if carried is not None else self._queue.get()
            carried = None
            if first is None:
                break
            batch = [first]
            deadline = time.monotonic() + self.settings.max_queue_delay_us / 1e6
            while len(batch) < self.settings.max_batch_size and not stopping:
                try:
                    item = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    break
                if item is None:
                    stopping = True
                elif item.labeler is not first.labeler:
                    carried = item
                    break
                else:
                    batch.append(item)
            self._execute(batch)
        while True:  # anything queued after close's marker (a racing caller) still gets answered
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item is not None:
                self._execute([item])

    def _execute(self, batch: list[_Queued]) -> None:
        try:
            results = batch[0].labeler.label_batch([q.frame for q in batch])
        except Exception as error:  # noqa: BLE001 - one frame's unforeseen error fails only it
            if len(batch) > 1:
                for queued in batch:
                    self._execute([queued])
                return
            results = [error]
        self.stats.batches += 1
        self.stats.frames += len(batch)
        self.stats.sizes[len(batch)] = self.stats.sizes.get(len(batch), 0) + 1
        for queued, result in zip(batch, results, strict=True):
            if isinstance(result, BaseException):
                queued.future.set_exception(result)
            else:
                queued.future.set_result(result)
