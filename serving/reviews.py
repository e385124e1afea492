"""Human labels: a reviewer's corrections of the auto-labels, imported from CVAT's 3D exports
(Sly Point Cloud, KITTI Raw, read with datumaro's own importers) or Label Studio's JSON export
(`detmatch review import`), kept beside the machine labels and never in place of them.

    STORE_ROOT/reviews/<namespace>/<frame id>.json   one frame's human labels: the source
                                                     format, reviewer and review time where
                                                     the export has them, the machine labels'
                                                     model version, and the labels (class,
                                                     3D box in the LiDAR frame and/or 2D box)

An import is all or nothing: every item is read and checked first (its frame is in the store,
its id is a valid key, its classes are known, its boxes are finite with positive sizes, and a
CVAT 3D item's camera matrices agree with the stored frame's calibration), and one error
anywhere writes nothing. The writes then go through a journal (`reviews/.import-*.json`,
written and fsynced first, removed last; an import killed in between is finished by the next
one), under a lock, so a crash never leaves half an import. Each frame's outcome follows the
store's rule: CREATED, UNCHANGED (the same labels, whoever imported them when) or REPLACED
(the previous human labels are said to be replaced, by frame id).
"""

from __future__ import annotations

import fcntl
import json
import math
import secrets
import time
from collections.abc import Iterable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from detmatch.constants import REVIEW_3D_FORMATS, REVIEW_CLASSES
from detmatch.files import atomic_write_bytes, fsync_path
from serving.review import DATUMARO_FORMAT, calib_of, camera_matrices, check_format, drawable
from serving.store_export import NAMESPACE_SEPARATOR, Store, list_frames, read_frame
from serving.store_index import store_files_root

REVIEWS_DIR = "reviews"
JOURNAL_PREFIX = ".import-"
# A related image's matrices and the stored calibration's may differ by the export's rounding.
CALIBRATION_TOLERANCE = 1e-5


@dataclass(frozen=True)
class HumanLabels:
    namespace: str
    frame_id: str
    source: str
    reviewer: str | None
    reviewed_at: str | None
    machine_version: str
    labels: tuple[dict[str, Any], ...]  # {"class", "box_3d": [7] | None, "box_2d": [4] | None}

    @property
    def key(self) -> tuple[str, str]:
        return self.namespace, self.frame_id

    def content(self) -> dict[str, Any]:
        """What decides UNCHANGED: the labels and where they came from, not when imported."""
        return {"source": self.source, "reviewer": self.reviewer,
                "reviewed_at": self.reviewed_at, "machine_version": self.machine_version,
                "labels": list(self.labels)}  # fmt: skip


@dataclass(frozen=True)
class ImportSummary:
    created: tuple[str, ...]
    unchanged: tuple[str, ...]
    replaced: tuple[str, ...]


class ReviewImportError(ValueError):
    """An export that cannot be imported; the message names every problem found (the first
    twenty), each with its frame."""


def review_path(root: Path, namespace: str, frame_id: str) -> Path:
    return root / REVIEWS_DIR / namespace / f"{frame_id}.json"


def read_human_labels(store: Store, namespace: str | None = None) -> dict[tuple, dict]:
    """Every frame's human labels (the stored JSON) by key, after finishing any import a crash
    interrupted."""
    root = store_files_root(store)
    if not (root / REVIEWS_DIR).is_dir():
        return {}
    if any((root / REVIEWS_DIR).glob(f"{JOURNAL_PREFIX}*.json")):
        with _locked(root):
            _finish_journals(root)
    found = {}
    for path in sorted((root / REVIEWS_DIR).glob("*/*.json")):
        record = json.loads(path.read_text())
        if namespace is None or record["namespace"] == namespace:
            found[(record["namespace"], record["frame_id"])] = record
    return found


def import_review(
    store: Store, source: str | Path, format: str, classes: Iterable[str] = REVIEW_CLASSES
) -> ImportSummary:
    """Read a reviewed export, check all of it, and store its human labels (see the module
    docstring)."""
    check_format(format)
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"--from {source}: no such file or directory")
    problems: list[str] = []
    if format == "label-studio":
        items = label_studio_items(_label_studio_tasks(source), problems)
    else:
        items = _cvat_items(source, format, problems)
    return store_reviews(store, items, format, classes, problems, str(source))


def store_reviews(
    store: Store,
    items: list,
    format: str,
    classes: Iterable[str] = REVIEW_CLASSES,
    problems: list[str] | None = None,
    source: str = "the export",
) -> ImportSummary:
    """Check every (item id, meta, labels) of a reviewed export against the store and store
    them as human labels, all or nothing (`ReviewImportError` naming every problem)."""
    problems = [] if problems is None else problems
    stored = {r.key: r for r in list_frames(store)}
    known = set(classes)
    reviews = []
    for item_id, meta, labels in items:
        key = _key(item_id, problems)
        if key is None:
            continue
        if key not in stored:
            problems.append(f"{item_id}: no such frame in the label store")
            continue
        for label in labels:
            _check_label(item_id, label, known, problems)
        if meta.get("camera") is not None:
            _check_camera(store, stored[key], item_id, meta["camera"], problems)
        reviews.append(HumanLabels(key[0], key[1], format, meta.get("reviewer"),
                                   meta.get("reviewed_at"), stored[key].model_version,
                                   tuple(labels)))  # fmt: skip
    seen: dict[tuple, int] = {}
    for review in reviews:
        seen[review.key] = seen.get(review.key, 0) + 1
    problems += [f"{ns}{NAMESPACE_SEPARATOR}{fid}: appears {n} times in the export"
                 for (ns, fid), n in seen.items() if n > 1]  # fmt: skip
    if not reviews and not problems:
        problems.append(f"{source}: the export holds no reviewed frame")
    if problems:
        shown = "; ".join(problems[:20])
        more = f" (and {len(problems) - 20} more)" if len(problems) > 20 else ""
        raise ReviewImportError(f"nothing was imported: {shown}{more}")
    return _write(store_files_root(store), reviews)


def _key(item_id: str, problems: list[str]) -> tuple[str, str] | None:
    from detmatch.data.kitti import validate_frame_id
    from serving.store import validate_namespace

    namespace, separator, frame_id = str(item_id).partition(NAMESPACE_SEPARATOR)
    try:
        if not separator:
            raise ValueError("expected NAMESPACE__FRAME_ID, as `detmatch review export` names")
        return validate_namespace(namespace), validate_frame_id(frame_id)
    except ValueError as error:
        problems.append(f"{str(item_id)[:80]!r}: not a frame key ({error})")
        return None


def _check_label(item_id: str, label: dict, known: set[str], problems: list[str]) -> None:
    if label["class"] not in known:
        problems.append(f"{item_id}: unknown class {label['class']!r} (known: "
                        f"{', '.join(sorted(known))})")  # fmt: skip
    box_3d, box_2d = label.get("box_3d"), label.get("box_2d")
    for name, box in (("3D box", box_3d), ("2D box", box_2d)):
        if box is not None and not all(math.isfinite(v) for v in box):
            problems.append(f"{item_id}: a {label['class']} {name} has a non-finite value")
            return
    if box_3d is not None and min(box_3d[3:6]) <= 0:
        problems.append(f"{item_id}: a {label['class']} 3D box has a size <= 0: {box_3d[3:6]}")
    if box_2d is not None and not drawable(box_2d):
        problems.append(f"{item_id}: a {label['class']} 2D box is empty: {box_2d}")


def _check_camera(store: Store, record, item_id: str, camera: dict, problems: list[str]) -> None:
    """The related image's matrices against the stored frame's calibration."""
    _, contents = read_frame(store, record, kinds=("calib",))
    intrinsic, extrinsic = camera_matrices(calib_of(next(iter(contents.values()))))
    for name, want in (("intrinsicMatrix", intrinsic), ("extrinsicMatrix", extrinsic)):
        got = np.asarray(camera.get(name, []), dtype=np.float64)
        if got.size != want.size or not np.allclose(got.reshape(want.shape), want,
                                                    rtol=CALIBRATION_TOLERANCE,
                                                    atol=CALIBRATION_TOLERANCE):  # fmt: skip
            problems.append(f"{item_id}: the related image's {name} disagrees with the stored "
                            "frame's calibration")  # fmt: skip


def _cvat_items(source: Path, format: str, problems: list[str]) -> list:
    try:
        import datumaro as dm
        from datumaro.components import annotation
    except ImportError:
        raise ValueError("CVAT's formats are read with datumaro: pip install "
                         "'detmatch[review]'") from None  # fmt: skip
    annotation.COORDINATE_ROUNDING_DIGITS = 6
    name = DATUMARO_FORMAT[format]
    try:
        dataset = dm.Dataset.import_from(str(source), name)
        items = list(dataset)
    except Exception as error:  # noqa: BLE001 - datumaro raises many kinds for a bad export
        raise ReviewImportError(
            f"nothing was imported: {source} is not a readable {format} export "
            f"({type(error).__name__}: {error})"
        ) from None
    categories = dataset.categories()[dm.AnnotationType.label]
    found = []
    for item in items:
        labels = []
        for shape in item.annotations:
            if shape.type != dm.AnnotationType.cuboid_3d:
                continue
            x, y, z = shape.position
            length, width, height = shape.scale
            labels.append({"class": categories[shape.label].name,
                           "box_3d": [float(v) for v in (x, y, z, length, width, height,
                                                          shape.rotation[2])],
                           "box_2d": None})  # fmt: skip
        meta: dict[str, Any] = {}
        if format == "cvat-3d":
            meta["camera"] = _related_camera(source, item.id)
            if meta["camera"] is None:
                problems.append(f"{item.id}: no related image with camera matrices")
        found.append((item.id, meta, labels))
    return found


def _related_camera(source: Path, item_id: str) -> dict | None:
    directory = source / "ds0" / "related_images" / f"{item_id}_pcd"
    for path in sorted(directory.glob("*.json")) if directory.is_dir() else []:
        data = json.loads(path.read_text())
        sensors = data.get("meta", {}).get("sensorsData")
        if sensors:
            return sensors
    return None


def _label_studio_tasks(source: Path) -> list:
    try:
        tasks = json.loads(source.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ReviewImportError(f"nothing was imported: {source} is not a Label Studio JSON "
                                f"export ({error})") from None  # fmt: skip
    if not isinstance(tasks, list):
        raise ReviewImportError(f"nothing was imported: {source} is not a list of tasks")
    return tasks


def label_studio_items(tasks: list, problems: list[str]) -> list:
    """Label Studio tasks (its JSON export, or a webhook's task with its annotation) -> the
    (item id, meta, labels) of each reviewed one: its latest annotation's boxes."""
    found = []
    for number, task in enumerate(tasks):
        data = task.get("data", {}) if isinstance(task, dict) else {}
        item_id = data.get("frame")
        annotations = [a for a in task.get("annotations", []) if not a.get("was_cancelled")] \
            if isinstance(task, dict) else []  # fmt: skip
        if item_id is None:
            problems.append(f"task {number}: no data.frame (not a `detmatch review export` task)")
            continue
        if not annotations:
            continue  # not reviewed yet
        latest = max(annotations, key=lambda a: a.get("updated_at") or a.get("created_at") or "")
        labels = []
        for result in latest.get("result", []):
            if result.get("type") != "rectanglelabels":
                continue
            try:
                value = result["value"]
                width, height = float(result["original_width"]), float(result["original_height"])
                x1, y1 = float(value["x"]) * width / 100, float(value["y"]) * height / 100
                box = [x1, y1, x1 + float(value["width"]) * width / 100,
                       y1 + float(value["height"]) * height / 100]  # fmt: skip
                names = [str(name) for name in value.get("rectanglelabels", [])]
            except (KeyError, TypeError, ValueError, AttributeError) as error:
                problems.append(f"{item_id}: a malformed rectangle result ({error!r})")
                continue
            for name in names:
                labels.append({"class": name, "box_3d": None,
                               "box_2d": [round(float(v), 4) for v in box]})  # fmt: skip
        reviewer = latest.get("completed_by")
        if isinstance(reviewer, dict):
            reviewer = reviewer.get("email") or reviewer.get("id")
        meta = {"reviewer": None if reviewer is None else str(reviewer),
                "reviewed_at": latest.get("updated_at") or latest.get("created_at")}  # fmt: skip
        found.append((item_id, meta, labels))
    return found


@contextmanager
def _locked(root: Path):
    directory = root / REVIEWS_DIR
    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / ".lock", "a+") as handle:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        yield


def _finish_journals(root: Path) -> None:
    """Apply every journal an import left (killed after writing it), then remove it."""
    for journal in sorted((root / REVIEWS_DIR).glob(f"{JOURNAL_PREFIX}*.json")):
        for record in json.loads(journal.read_text()):
            atomic_write_bytes(review_path(root, record["namespace"], record["frame_id"]),
                               json.dumps(record, indent=2).encode())  # fmt: skip
        journal.unlink()
        fsync_path(journal.parent)


def _write(root: Path, reviews: list[HumanLabels]) -> ImportSummary:
    imported_at = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    created, unchanged, replaced, records = [], [], [], []
    with _locked(root):
        _finish_journals(root)
        for review in reviews:
            path = review_path(root, review.namespace, review.frame_id)
            name = f"{review.namespace}{NAMESPACE_SEPARATOR}{review.frame_id}"
            if path.is_file():
                held = json.loads(path.read_text())
                if {k: held.get(k) for k in review.content()} == review.content():
                    unchanged.append(name)
                    continue
                replaced.append(name)
            else:
                created.append(name)
            records.append({"namespace": review.namespace, "frame_id": review.frame_id,
                            **review.content(), "imported_at": imported_at})  # fmt: skip
        if records:
            journal = root / REVIEWS_DIR / f"{JOURNAL_PREFIX}{secrets.token_hex(6)}.json"
            atomic_write_bytes(journal, json.dumps(records).encode())
            _finish_journals(root)
    return ImportSummary(tuple(created), tuple(unchanged), tuple(replaced))


def review_digest(record: dict) -> str:
    """A stored review's content digest (what a retraining snapshot folds in): its labels and
    where they came from, not when they were imported."""
    import hashlib

    content = {k: v for k, v in record.items() if k != "imported_at"}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def has_3d_review(record: dict) -> bool:
    """A review that fixes a frame's 3D labels: a CVAT one (its boxes, possibly none: the
    reviewer found nothing); a Label Studio review has 2D boxes only."""
    return record["source"] in REVIEW_3D_FORMATS


def human_label_rows(record: dict, calib, image_size: tuple[int, int]):
    """A 3D review's labels as KITTI label rows (no score; truncation and occlusion 0: a
    reviewer's box is a fully labeled object), the camera's view only, as KITTI labels."""
    import dataclasses

    from detmatch.data.results import result_objects_3d

    labels = [lb for lb in record["labels"] if lb.get("box_3d") is not None]
    boxes = np.array([lb["box_3d"] for lb in labels], dtype=np.float64).reshape(-1, 7)
    rows = result_objects_3d(boxes, [lb["class"] for lb in labels], np.zeros(len(labels)),
                             calib, image_size)  # fmt: skip
    return dataclasses.replace(rows, score=None, truncated=np.zeros(len(rows)),
                               occluded=np.zeros(len(rows), dtype=np.int64))  # fmt: skip
