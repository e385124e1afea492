"""Review in a real Label Studio (local, SQLite): the exported tasks and their pre-annotations
go in through its API, a reviewer's annotation comes out of its export into the label store
as human labels, and `detmatch review backend` answers Label Studio's own setup / predict
calls and its START_TRAINING webhook with exactly one retraining round."""

from __future__ import annotations

import copy
import json
import os

import pytest

if os.environ.get("DETMATCH_REQUIRE_REVIEW"):  # .ci/run installs the review extra
    import datumaro  # noqa: F401
else:
    pytest.importorskip("aiohttp", reason="the review extra: pip install -e '.[review]'")

from commands.main import main  # noqa: E402
from serving.repository import list_versions  # noqa: E402
from serving.review import export_review, select_frames  # noqa: E402
from serving.reviews import read_human_labels  # noqa: E402
from tests.review.label_studio import (  # noqa: E402
    ROUND_OVERRIDES,
    backend_process,
    file_server,
    label_studio_server,
    wait_for_rounds,
)


@pytest.fixture
def label_studio(tmp_path):
    directory = tmp_path / "label-studio"
    directory.mkdir()
    with label_studio_server(directory) as server:
        yield server


def _tasks(label_studio, project_id: int) -> list[dict]:
    answer = label_studio.call("GET", f"/api/tasks?project={project_id}&page_size=100&fields=all")
    return answer["tasks"] if isinstance(answer, dict) else answer


def test_a_review_round_trip_and_the_backend_in_a_real_label_studio(
    tmp_path,
    store,
    repository,
    round_data,
    label_studio,
):
    export = tmp_path / "ls-export"
    with file_server(export) as images:
        chosen = select_frames(store, namespace="default")
        export_review(store, export, "label-studio", chosen, image_url_prefix=images)
        config = (export / "label_config.xml").read_text()
        project = label_studio.call(
            "POST", "/api/projects", {"title": "detmatch review", "label_config": config}
        )
        tasks = json.loads((export / "tasks.json").read_text())
        label_studio.call("POST", f"/api/projects/{project['id']}/import", tasks)
        imported = {t["data"]["frame"]: t for t in _tasks(label_studio, project["id"])}
        assert set(imported) == {"default__000000", "default__000001", "default__000002"}

        # The reviewer takes 000001's pre-annotation, moves its first box 10 pixels right and
        # adds a Pedestrian.
        task = imported["default__000001"]
        (prediction,) = label_studio.call("GET", f"/api/predictions?task={task['id']}")
        assert prediction["model_version"] == "000001" and prediction["result"]
        result = copy.deepcopy(prediction["result"])
        moved = result[0]["value"]
        moved["x"] += 100 * 10 / result[0]["original_width"]
        pedestrian = copy.deepcopy(result[0])
        pedestrian.update(id="added")
        pedestrian["value"].update(x=10.0, y=20.0, width=2.0, height=8.0,
                                   rectanglelabels=["Pedestrian"])  # fmt: skip
        label_studio.call("POST", f"/api/tasks/{task['id']}/annotations",
                          {"result": result + [pedestrian], "lead_time": 12.5})  # fmt: skip

        exported = label_studio.call(
            "GET", f"/api/projects/{project['id']}/export?exportType=JSON&download_all_tasks=true"
        )
        source = tmp_path / "label-studio-export.json"
        source.write_text(json.dumps(exported))
        assert main(["review", "import", "--store", str(store), "--from", str(source),
                     "--format", "label-studio"]) == 0  # fmt: skip
        human = read_human_labels(store)
        assert set(human) == {("default", "000001")}  # only the reviewed task
        record = human[("default", "000001")]
        assert record["source"] == "label-studio" and record["reviewer"]
        width = result[0]["original_width"]
        reviewed = next(s for s in chosen if s.record.frame_id == "000001")
        stored_box = reviewed.labels["labels"][
            int(prediction["result"][0]["id"].rsplit("-", 1)[1])
        ]["box_2d"]
        boxes = {(lb["class"], round(lb["box_2d"][0], 2)) for lb in record["labels"]}
        assert (result[0]["value"]["rectanglelabels"][0], round(stored_box[0] + 10, 2)) in boxes
        assert ("Pedestrian", round(10.0 * width / 100, 2)) in boxes
        assert len(record["labels"]) == len(result) + 1

        # The backend, connected the way a Label Studio user connects it.
        with backend_process(
            "--repository",
            str(repository),
            "--store",
            str(store),
            "--data",
            str(round_data),
            *ROUND_OVERRIDES,
        ) as (url, printed):
            backend = label_studio.call("POST", "/api/ml", {"url": url, "project": project["id"],
                                                            "title": "detmatch"})  # fmt: skip
            label_studio.call(
                "POST", f"/api/dm/actions?id=retrieve_tasks_predictions&project={project['id']}",
                {"project": str(project["id"]), "selectedItems": {"all": True, "excluded": []}},
            )  # fmt: skip
            for frame, task in imported.items():
                versions = [
                    p["model_version"]
                    for p in label_studio.call("GET", f"/api/predictions?task={task['id']}")
                ]
                # the export's pre-annotation (the cross-modal labels) and the backend's (the
                # camera detector alone) of version 000001
                assert sorted(versions) == ["000001", "000001-camera"], (frame, versions, printed)

            label_studio.call("POST", f"/api/ml/{backend['id']}/train", {})
            (finished,) = wait_for_rounds(url, 1)
            assert finished["exit_code"] == 0, finished["output"]
            assert finished["reason"] == "START_TRAINING"
            assert "version 000002 promoted" in finished["output"]
    assert list_versions(repository) == ["000001", "000002"]
