"""`detmatch review import`: a reviewer's CVAT 3D edits (a moved, a deleted, an added box and a
changed class) come back as exactly those human labels, beside the machine labels; re-imports
say unchanged / replaced; Label Studio's JSON export brings 2D corrections with the reviewer;
and every bad export is refused naming the frame, with nothing imported."""

from __future__ import annotations

import json
import os
import shutil

import pytest

if os.environ.get("DETMATCH_REQUIRE_REVIEW"):  # .ci/run installs the review extra
    import datumaro as dm
else:
    dm = pytest.importorskip("datumaro", reason="the review extra: pip install -e '.[review]'")

from commands.main import main  # noqa: E402
from serving.review import export_review, select_frames  # noqa: E402
from serving.reviews import ReviewImportError, import_review, read_human_labels  # noqa: E402
from serving.store import list_frames  # noqa: E402

FRAME = "default__000001"


def _edited_cvat(store, tmp_path, edit):
    """A cvat-3d export, changed with datumaro as a reviewer would in CVAT, written back with
    the export's camera matrices (CVAT keeps them; datumaro writes zeros)."""
    from datumaro.components import annotation

    exported = tmp_path / "exported"
    if not exported.is_dir():
        export_review(store, exported, "cvat-3d", select_frames(store, namespace="default"))
    annotation.COORDINATE_ROUNDING_DIGITS = 6
    dataset = dm.Dataset.import_from(str(exported), "sly_pointcloud")
    classes = dataset.categories()[dm.AnnotationType.label]
    edit(dataset, classes)
    out = tmp_path / f"edited{len(list(tmp_path.glob('edited*')))}"
    dataset.export(str(out), "sly_pointcloud", save_media=True, allow_undeclared_attrs=True)
    for camera in exported.glob("ds0/related_images/*/*.json"):
        target = out / camera.relative_to(exported)
        if target.parent.is_dir():
            shutil.copyfile(camera, target)
    return out


def _cuboid(box, **changes):
    """A copy of a cuboid with some fields changed (Cuboid3d.wrap fails on attrs 25)."""
    fields = {
        "position": list(box.position),
        "rotation": list(box.rotation),
        "scale": list(box.scale),
        "label": box.label,
        "attributes": dict(box.attributes),
    }
    return dm.Cuboid3d(**{**fields, **changes})  # fmt: skip


def _review(dataset, classes):
    item = dataset.get(FRAME)
    boxes = list(item.annotations)
    moved = _cuboid(boxes[0], position=[boxes[0].position[0] + 1.0, *boxes[0].position[1:]])
    relabeled = _cuboid(boxes[2], label=classes.find("Cyclist")[0]) if len(boxes) > 2 else None
    added = dm.Cuboid3d(position=[12.0, -3.0, -0.8], rotation=[0.0, 0.0, 0.5],
                        scale=[0.8, 0.6, 1.7], label=classes.find("Pedestrian")[0],
                        attributes={"track_id": 999})  # fmt: skip
    kept = [moved] + ([relabeled] if relabeled is not None else []) + boxes[3:] + [added]
    dataset.put(item.wrap(annotations=kept))  # boxes[1] is deleted


def test_cvat_edits_come_back_as_exactly_those_human_labels(store, tmp_path, capsys):
    machine = {s.record.key: s.labels for s in select_frames(store)}
    before = machine[("default", "000001")]["labels"]
    assert len(before) >= 3, "the edit needs three machine labels to move, delete and relabel"
    edited = _edited_cvat(store, tmp_path, _review)
    summary = import_review(store, edited, "cvat-3d")
    assert len(summary.created) == 3 and not summary.unchanged and not summary.replaced
    human = read_human_labels(store)[("default", "000001")]
    assert human["source"] == "cvat-3d" and human["machine_version"] == "000001"
    got = sorted((lb["class"], [round(v, 3) for v in lb["box_3d"]]) for lb in human["labels"])
    moved = [before[0]["box_3d"][0] + 1.0, *before[0]["box_3d"][1:]]
    want = sorted(
        [(before[0]["class_3d"], [round(v, 3) for v in moved]),
         ("Cyclist", [round(v, 3) for v in before[2]["box_3d"]]),
         *[(lb["class_3d"], [round(v, 3) for v in lb["box_3d"]]) for lb in before[3:]],
         ("Pedestrian", [12.0, -3.0, -0.8, 0.8, 0.6, 1.7, 0.5])]
    )  # fmt: skip
    assert got == want
    # beside the machine labels, never in place of them
    assert {s.record.key: s.labels for s in select_frames(store)} == machine

    assert main(["review", "import", "--store", str(store), "--from", str(edited), "--format",
                 "cvat-3d"]) == 0  # fmt: skip
    assert "0 created, 3 unchanged, 0 replaced" in capsys.readouterr().out

    def second(dataset, classes):
        item = dataset.get(FRAME)
        dataset.put(item.wrap(annotations=list(item.annotations)[:1]))

    again = _edited_cvat(store, tmp_path, second)
    summary = import_review(store, again, "cvat-3d")
    assert summary.replaced == (FRAME,) and len(summary.unchanged) == 2
    assert len(read_human_labels(store)[("default", "000001")]["labels"]) == 1


def _refused(store, source, format, match):
    with pytest.raises(ReviewImportError, match=match):
        import_review(store, source, format)
    assert read_human_labels(store) == {}  # nothing half-imported


def test_bad_cvat_exports_are_refused_naming_the_frame(store, tmp_path):
    def unknown(dataset, classes):
        item = dataset.get(FRAME)
        dataset.remove(FRAME)
        dataset.put(item.wrap(id="default__999999"))

    _refused(store, _edited_cvat(store, tmp_path, unknown), "cvat-3d",
             "default__999999: no such frame in the label store")  # fmt: skip

    def negative(dataset, classes):
        item = dataset.get(FRAME)
        box = item.annotations[0]
        dataset.put(item.wrap(annotations=[_cuboid(box, scale=[-1.0, 1.0, 1.0])]))

    _refused(store, _edited_cvat(store, tmp_path, negative), "cvat-3d",
             f"{FRAME}: a .* 3D box has a size <= 0")  # fmt: skip

    moved_camera = _edited_cvat(store, tmp_path, lambda dataset, classes: None)
    (meta,) = (moved_camera / "ds0" / "related_images" / f"{FRAME}_pcd").glob("*.json")
    data = json.loads(meta.read_text())
    data["meta"]["sensorsData"]["extrinsicMatrix"][3] += 0.5
    meta.write_text(json.dumps(data))
    _refused(store, moved_camera, "cvat-3d",
             f"{FRAME}: the related image's extrinsicMatrix disagrees")  # fmt: skip

    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "meta.json").write_text("{not json")
    _refused(store, garbage, "cvat-3d", "is not a readable cvat-3d export")


def _label_studio_export(store, tmp_path):
    """Label Studio's JSON export of the exported tasks after a reviewer's annotation."""
    out = tmp_path / "ls"
    export_review(store, out, "label-studio", select_frames(store))
    tasks = json.loads((out / "tasks.json").read_text())
    for index, task in enumerate(tasks):
        results = task["predictions"][0]["result"][:1]
        task["id"] = index + 1
        task["annotations"] = [{"id": index + 1, "completed_by": {"id": 1, "email": "r@x.io"},
                                "updated_at": "2026-12-07T10:00:00Z", "result": results,
                                "was_cancelled": False}] if results else []  # fmt: skip
    return tasks


def test_label_studio_corrections_come_back_with_the_reviewer(store, tmp_path):
    tasks = _label_studio_export(store, tmp_path)
    path = tmp_path / "export.json"
    path.write_text(json.dumps(tasks))
    summary = import_review(store, path, "label-studio")
    reviewed = [t for t in tasks if t["annotations"]]
    assert len(summary.created) == len(reviewed) > 0
    for task in reviewed:
        namespace, _, frame_id = task["data"]["frame"].partition("__")
        human = read_human_labels(store)[(namespace, frame_id)]
        (label,) = human["labels"]
        result = task["annotations"][0]["result"][0]
        assert human["reviewer"] == "r@x.io" and human["reviewed_at"] == "2026-12-07T10:00:00Z"
        assert label["class"] == result["value"]["rectanglelabels"][0] and label["box_3d"] is None
        value, width = result["value"], result["original_width"]
        assert label["box_2d"][0] == pytest.approx(value["x"] * width / 100, abs=1e-3)


def test_bad_label_studio_exports_are_refused(store, tmp_path):
    tasks = _label_studio_export(store, tmp_path)
    reviewed = next(t for t in tasks if t["annotations"])
    cases = [
        ("../../etc__passwd", None, "not a frame key"),
        (reviewed["data"]["frame"], -5.0, "2D box is empty"),
    ]
    for frame, width, match in cases:
        bad = json.loads(json.dumps(tasks))
        target = next(t for t in bad if t["data"]["frame"] == reviewed["data"]["frame"])
        target["data"]["frame"] = frame
        if width is not None:
            target["annotations"][0]["result"][0]["value"]["width"] = width
        path = tmp_path / "bad.json"
        path.write_text(json.dumps(bad))
        _refused(store, path, "label-studio", match)
    path.write_text("[{")
    _refused(store, path, "label-studio", "not a Label Studio JSON export")
    assert len(list_frames(store)) == 4
