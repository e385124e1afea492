"""Dynamic batching on a real server: concurrent calls with different frames are labeled in
shared graph calls, each caller gets its own frame's labels, and a bad frame fails only its
own call."""

from __future__ import annotations

import threading

import grpc
import numpy as np
import pytest

from detmatch.data.kitti import KittiDataset
from serving.batching import Batcher, BatchingSettings
from serving.client import LabelingClient, kitti_frame
from serving.config import ServerConfig
from serving.labeler import Frame
from serving.request import LabelOptions
from serving.service import ModelSlot
from tests.conftest import KITTI_SAMPLE
from tests.grpc_service.conftest import running_server

OPTIONS = LabelOptions(score_threshold_2d=0.01, score_threshold_3d=0.01, tau_hung=10.0)
BAD = LabelOptions(score_threshold_2d=1.5)


def _sources(synth_root):
    return [(synth_root, i) for i in KittiDataset(synth_root).ids()[:3]] + [
        (KITTI_SAMPLE, "000001")
    ]


def _call_together(target: str, requests: list) -> list:
    """Every request on its own thread, released at once; each one's response or RpcError."""
    results: list = [None] * len(requests)
    barrier = threading.Barrier(len(requests))

    def call(i: int) -> None:
        with LabelingClient(target) as client:
            barrier.wait()
            try:
                results[i] = client.label_frame(requests[i])
            except grpc.RpcError as error:
                results[i] = error

    threads = [threading.Thread(target=call, args=(i,)) for i in range(len(requests))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    return results


def test_concurrent_calls_share_batches_and_each_gets_its_own_labels(
    tmp_path, served_labeler, synth_root
):
    slot = ModelSlot()
    slot.swap(served_labeler)
    sources = _sources(synth_root)
    requests = [kitti_frame(root, i, options=OPTIONS) for root, i in sources]
    requests.insert(2, kitti_frame(*sources[1], options=BAD))
    config = ServerConfig(workers=5, max_batch_size=5, max_queue_delay_us=500_000)
    with running_server(slot, tmp_path / "store", config) as server:
        results = _call_together(server.target, requests)
        stats = server.service.batcher.stats
    assert isinstance(results[2], grpc.RpcError)
    assert results[2].code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "score_threshold_2d" in results[2].details()
    good = results[:2] + results[3:]
    assert max(stats.sizes) >= 2, stats  # calls did share graph calls
    assert stats.frames == len(requests)
    for (root, frame_id), response in zip(sources, good, strict=True):
        assert response.frame_id == frame_id
        frame = KittiDataset(root).load_frame(frame_id, with_labels=False)
        alone = served_labeler.label(frame.image, frame.points, frame.calib,
                                     score_threshold_2d=0.01, score_threshold_3d=0.01,
                                     tau_hung=10.0)  # fmt: skip
        assert len(response.labels) == len(alone) > 0
        got = np.array(
            [[b.x, b.y, b.z, b.l, b.w, b.h] for b in (x.box_3d for x in response.labels)]
        )
        np.testing.assert_allclose(
            got[np.lexsort(got.T)],
            alone.labels.boxes_3d[:, :6][np.lexsort(alone.labels.boxes_3d[:, :6].T)],
            atol=1e-3,
        )


def test_a_batch_that_raises_is_labeled_frame_by_frame(served_labeler, synth_root):
    """An error no input check foresaw (here: the 3D graph fails on one frame's cloud) fails
    only that frame's call: the batcher labels the batch's frames one by one."""

    class Flaky:
        """The served labeler, except that a cloud of exactly 7 points breaks the 3D graph."""

        version = served_labeler.version

        def label_batch(self, frames):
            if len(frames) > 1 and any(len(f.points) == 7 for f in frames):
                raise RuntimeError("onnxruntime: a kernel failed")
            if len(frames[0].points) == 7:
                raise RuntimeError("onnxruntime: a kernel failed")
            return served_labeler.label_batch(frames)

    frame = KittiDataset(synth_root).load_frame("000000")
    frames = [Frame(frame.image, frame.points, frame.calib),
              Frame(frame.image, frame.points[:7], frame.calib),
              Frame(frame.image, frame.points[:500], frame.calib)]  # fmt: skip
    batcher = Batcher(BatchingSettings(max_batch_size=3, max_queue_delay_us=500_000))
    flaky = Flaky()
    results: list = [None] * 3

    def call(i: int) -> None:
        try:
            results[i] = batcher.label(flaky, frames[i])
        except RuntimeError as error:
            results[i] = error

    threads = [threading.Thread(target=call, args=(i,)) for i in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    batcher.close()
    assert isinstance(results[1], RuntimeError)
    assert results[0].batch_size == results[2].batch_size == 1
    alone = served_labeler.label(frame.image, frame.points, frame.calib)
    np.testing.assert_allclose(results[0].detections_3d.scores, alone.detections_3d.scores)
    with pytest.raises(RuntimeError, match="closed"):
        batcher.label(flaky, frames[0])


def test_batching_settings_are_checked():
    with pytest.raises(ValueError, match="max_batch_size must be >= 1"):
        BatchingSettings(max_batch_size=0)
    with pytest.raises(ValueError, match="max_queue_delay_us must be >= 0"):
        BatchingSettings(max_batch_size=2, max_queue_delay_us=-1)
    with pytest.raises(ValueError, match="exceeds workers 4"):
        ServerConfig(workers=4, max_batch_size=8)
    with pytest.raises(ValueError, match="needs max_batch_size >= 2"):
        Batcher(BatchingSettings())
