"""LabelingService without gRPC: a FrameRequest in, the labels and what the store did out; the
two halves a server runs on its two thread pools; the domain errors the servicer maps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from detmatch.data.kitti import KittiDataset
from serving.errors import InvalidInput, ModelUnavailable
from serving.request import FrameRequest, LabelOptions
from serving.service import LabelingService, ModelSlot
from serving.store import LabelStore, StoreOutcome, list_frames
from tests.conftest import KITTI_SAMPLE


def _request(frame_id: str = "000001", **options) -> FrameRequest:
    dataset = KittiDataset(KITTI_SAMPLE)
    frame = dataset.load_frame(frame_id, with_labels=False)
    image = dataset.image_path(frame_id).read_bytes()
    return FrameRequest.from_arrays(
        frame_id, image, frame.points, frame.calib, options=LabelOptions(**options)
    )


@pytest.fixture
def slot(served_labeler) -> ModelSlot:
    slot = ModelSlot()
    slot.swap(served_labeler)
    return slot


def test_label_frame_labels_as_the_labeler_and_stores(tmp_path, slot, served_labeler):
    store = LabelStore(tmp_path, "s0")
    service = LabelingService(slot, store)
    frame = KittiDataset(KITTI_SAMPLE).load_frame("000001", with_labels=False)
    low = {"score_threshold_2d": 0.01, "score_threshold_3d": 0.01, "tau_hung": 10.0}
    expected = served_labeler.label(frame.image, frame.points, frame.calib, **low)
    result = service.label_frame(_request(**low))  # the test model's scores are all low
    not_stored = service.label_frame(_request(store=False))
    store.close()
    assert (result.namespace, result.frame_id) == ("default", "000001")
    assert result.result.model_version == served_labeler.version
    assert len(result.result) == len(expected) > 0
    np.testing.assert_allclose(result.result.labels.boxes_3d, expected.labels.boxes_3d)
    assert result.stored.outcome == StoreOutcome.CREATED and not_stored.stored is None
    stages = ("decode", "detector2d", "pillarize", "detector3d", "matching", "store")
    assert all(result.timings[s] >= 0 for s in stages)
    assert result.timings["total"] >= result.timings["decode"] + result.timings["store"]
    assert [r.frame_id for r in list_frames(tmp_path)] == ["000001"]


def test_labeling_touches_no_disk_and_storing_is_the_second_half(tmp_path, slot):
    """The server runs `label` on its inference threads and `store_labels` on its I/O
    threads; only the second writes, and only when the request asks and a store exists."""
    store = LabelStore(tmp_path, "s0")
    service = LabelingService(slot, store)
    labeled = service.label(_request("000002"))
    assert labeled.stores and list_frames(tmp_path) == []
    assert service.store_labels(labeled).stored.outcome == StoreOutcome.CREATED
    assert not service.label(_request("000002", store=False)).stores
    store.close()
    assert [r.frame_id for r in list_frames(tmp_path)] == ["000002"]
    assert not LabelingService(slot, None).label(_request()).stores


def test_bad_input_names_the_field_and_no_model_is_unavailable(slot):
    service = LabelingService(slot, None)
    with pytest.raises(InvalidInput, match="^frame_id: "):
        service.label(dataclasses.replace(_request(), frame_id="../x"))
    with pytest.raises(InvalidInput, match="^calibration.p2: expected 12 values, got 11"):
        service.label(dataclasses.replace(_request(), p2=[1.0] * 11))
    with pytest.raises(InvalidInput, match="^options.score_threshold_3d"):
        service.label(_request(score_threshold_3d=1.5))
    with pytest.raises(ModelUnavailable):
        LabelingService(ModelSlot(), None).label(_request())
