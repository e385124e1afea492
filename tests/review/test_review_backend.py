"""`detmatch review backend` as a process on a real socket, called as Label Studio calls it:
health, setup, predict (images as data URIs), annotation webhooks into the label store, bad
input, and training requests: one round at a time, under the repository's retraining lock."""

from __future__ import annotations

import base64
import os
import time

import numpy as np
import pytest
from PIL import Image

if os.environ.get("DETMATCH_REQUIRE_REVIEW"):  # .ci/run installs the review extra
    import aiohttp  # noqa: F401
else:
    pytest.importorskip("aiohttp", reason="the review extra: pip install -e '.[review]'")

from detmatch.data.kitti import KittiDataset  # noqa: E402
from retrain.schedule import retrain_lock  # noqa: E402
from serving.repository import list_versions  # noqa: E402
from serving.review import label_studio_config  # noqa: E402
from serving.reviews import read_human_labels  # noqa: E402
from tests.conftest import KITTI_SAMPLE  # noqa: E402
from tests.review.label_studio import (  # noqa: E402
    ROUND_OVERRIDES,
    backend_process,
    http_json,
    wait_for_rounds,
)

CONFIG = label_studio_config(["Car", "Pedestrian", "Cyclist"])


def _data_uri(frame_id: str) -> str:
    png = KittiDataset(KITTI_SAMPLE).image_path(frame_id).read_bytes()
    return "data:image/png;base64," + base64.b64encode(png).decode()


def _annotation(box=(100.0, 120.0, 160.0, 200.0), name="Car", width=1242, height=375) -> dict:
    x1, y1, x2, y2 = box
    return {"id": 7, "completed_by": 3, "created_at": "2026-12-07T10:00:00Z", "result": [{
        "id": "r1", "type": "rectanglelabels", "from_name": "label", "to_name": "image",
        "original_width": width, "original_height": height,
        "value": {"x": 100 * x1 / width, "y": 100 * y1 / height, "width": 100 * (x2 - x1) / width,
                  "height": 100 * (y2 - y1) / height, "rectanglelabels": [name]}}]}  # fmt: skip


def _webhook(frame: str, annotation: dict) -> dict:
    return {"action": "ANNOTATION_CREATED", "project": {"id": 1},
            "task": {"id": 1, "data": {"image": "unused", "frame": frame}},
            "annotation": annotation}  # fmt: skip


def test_setup_predict_and_bad_requests(exported_repository):
    with backend_process("--repository", str(exported_repository)) as (url, _):
        assert http_json("GET", url + "/health") == (
            200, {"status": "UP", "model_class": "DetMatch", "model_version": "000001-camera",
                  "training": None})  # fmt: skip
        assert http_json("POST", url + "/setup", {"project": "4.1700000000", "schema": CONFIG}) \
            == (200, {"model_version": "000001-camera"})  # fmt: skip
        status, answer = http_json(
            "POST", url + "/setup", {"project": "4.1", "schema": "<View><Text name='t'/></View>"}
        )
        assert status == 400 and "no RectangleLabels on an Image" in answer["error"]

        tasks = [{"id": n, "data": {"image": _data_uri(frame)}} for n, frame in
                 enumerate(("000000", "000001"))]  # fmt: skip
        status, answer = http_json("POST", url + "/predict", {"tasks": tasks, "project": "4.1"})
        assert status == 200 and len(answer["results"]) == 2
        for frame, result in zip(("000000", "000001"), answer["results"], strict=True):
            size = Image.open(KittiDataset(KITTI_SAMPLE).image_path(frame)).size
            assert result["model_version"] == "000001-camera" and result["result"]
            for region in result["result"]:
                value = region["value"]
                assert region["from_name"] == "label" and region["to_name"] == "image"
                assert value["rectanglelabels"][0] in ("Car", "Pedestrian", "Cyclist")
                assert 0 <= value["x"] <= 100 and 0 < value["width"] <= 100 - value["x"] + 1e-6
                assert (region["original_width"], region["original_height"]) == size

        # A project whose interface names only Cyclist gets only Cyclist boxes.
        only = label_studio_config(["Cyclist"])
        status, answer = http_json("POST", url + "/predict",
                                   {"tasks": tasks[:1], "label_config": only})  # fmt: skip
        assert status == 200
        assert {r["value"]["rectanglelabels"][0] for r in answer["results"][0]["result"]} <= {
            "Cyclist"
        }

        for body, message in (
            (b"{not json", "not JSON"),
            ({"tasks": "x", "project": "4.1"}, "a list of tasks"),
            ({"tasks": [{"data": {}}], "project": "4.1"}, "no data.image"),
            ({"tasks": [{"data": {"image": "data:image/png;base64,@@@"}}], "project": "4.1"},
             "does not decode"),
            ({"tasks": [{"data": {"image": "data:image/png;base64,aGVsbG8="}}], "project": "4.1"},
             "not an image"),
            ({"tasks": [{"data": {"image": "/data/upload/1/x.png"}}], "project": "9"},
             "needs a label_config"),
            ({"tasks": [{"data": {"image": "/data/upload/1/x.png"}}], "label_config": CONFIG},
             "no hostname"),
        ):  # fmt: skip
            status, answer = http_json("POST", url + "/predict", body)
            assert status == 400 and message in answer["error"], (body, answer)
        status, answer = http_json("POST", url + "/webhook", {"action": "START_TRAINING"})
        assert status == 400 and "training needs --data and --store" in answer["error"]
        # Events it does not act on are acknowledged.
        assert http_json("POST", url + "/webhook", {"action": "PROJECT_UPDATED"}) == (
            201,
            {"action": "PROJECT_UPDATED", "ignored": "PROJECT_UPDATED"},
        )


def test_annotations_become_human_labels_and_training_waits_for_the_lock(
    store,
    repository,
    round_data,
):
    args = ["--repository", str(repository), "--store", str(store), "--data", str(round_data),
            "--train-after", "2", "--lock-retry-s", "0.2", *ROUND_OVERRIDES]  # fmt: skip
    with backend_process(*args) as (url, printed):
        # Bad annotations are refused whole, naming the frame; nothing is stored.
        for frame, annotation, message in (
            ("default__999999", _annotation(), "no such frame in the label store"),
            ("default__../../etc", _annotation(), "default__../../etc"),
            ("default__000001", _annotation(name="Tram"), "unknown class 'Tram'"),
            ("default__000001", _annotation(box=(50, 60, 50, 90)), "2D box is empty"),
            ("default__000001", {"result": [{"type": "rectanglelabels", "value": {}}]},
             "malformed rectangle"),
        ):  # fmt: skip
            status, answer = http_json("POST", url + "/webhook", _webhook(frame, annotation))
            assert status == 422 and message in answer["error"], (frame, answer)
        assert read_human_labels(store) == {}
        status, answer = http_json("POST", url + "/webhook", {"action": "ANNOTATION_CREATED"})
        assert status == 400 and "without a task and an annotation" in answer["error"]
        status, answer = http_json("POST", url + "/webhook", {
            "action": "ANNOTATION_CREATED", "task": {"id": 3, "data": {"image": "x"}},
            "annotation": _annotation()})  # fmt: skip
        assert status == 201 and answer["stored"] is False and "no data.frame" in answer["why"]

        with retrain_lock(repository):  # another scheduler holds the repository
            status, answer = http_json("POST", url + "/webhook",
                                       _webhook("default__000001", _annotation()))  # fmt: skip
            assert status == 201 and answer["created"] == ["default__000001"]
            assert "training" not in answer  # 1 of --train-after 2
            status, answer = http_json("POST", url + "/webhook",
                                       _webhook("default__000001", _annotation()))  # fmt: skip
            assert answer["unchanged"] == ["default__000001"] and answer["training"] == "started"
            # More requests while that round waits coalesce into one round after it (or into
            # it, once it was refused the lock).
            for _ in range(2):
                assert http_json("POST", url + "/webhook", {"action": "START_TRAINING"})[1][
                    "training"] in ("queued", "already queued")  # fmt: skip
            deadline = time.monotonic() + 120
            _, health = http_json("GET", url + "/health")
            while not health["training"]["waiting"]:  # the round was refused the lock
                assert time.monotonic() < deadline, health
                time.sleep(0.1)
                _, health = http_json("GET", url + "/health")
            assert "another retraining holds" in health["training"]["waiting"]
            assert health["training"]["rounds"] == [] and health["training"]["queued"]
        (finished,) = wait_for_rounds(url, 1)
        assert finished["exit_code"] == 0, (finished["output"], printed)
        assert finished["reason"] == "2 new annotations; START_TRAINING"
    human = read_human_labels(store)[("default", "000001")]
    (label,) = human["labels"]
    assert label["class"] == "Car" and label["box_3d"] is None
    assert np.allclose(label["box_2d"], [100, 120, 160, 200], atol=1e-3)
    assert human["reviewer"] == "3" and human["source"] == "label-studio"
    assert list_versions(repository) == ["000001", "000002"]
