"""Auto-labels out for human review (`detmatch review export`): CVAT's 3D formats (Sly Point
Cloud, with the camera image and its calibration; KITTI Raw) and Label Studio's task import
format (the image with 2D pre-annotations). Torch-free; CVAT's formats are written with
`datumaro` (the `review` extra), the library CVAT's own import uses.

Which frames (`select_frames`): every stored frame of the filters (namespace, model version),
a seeded random audit sample of --budget, the --budget frames whose labels have the lowest
mean 3D score (`low_confidence`: what a single-modality labeler can rank by), or the --budget
frames where the 2D and 3D teachers disagree most (`disagreement`: camera detections no label
took, LiDAR-only labels in view, class disagreements, weak matches). Each selected frame
carries the reason it was picked.

Every cuboid and box carries its label's provenance (matched / LiDAR-only), scores, matching
cost and the model version as attributes, so a reviewer can sort and filter by doubt.

Coordinates. A Sly Point Cloud cuboid is the label's LiDAR-frame box: position = the gravity
centre (x, y, z), scale = (l, w, h), rotation = (0, 0, yaw), as the store keeps it. datumaro
rounds cuboids to 2 decimals unless told otherwise (`COORDINATE_ROUNDING_DIGITS`), and writes
zeros for the related image's camera matrices: this module keeps 6 decimals and writes the
matrices itself, intrinsic = P2's left 3 x 3 block K, extrinsic = K^-1 P2 R0_rect
Tr_velo_to_cam (3 x 4, LiDAR -> camera 2), so that K . extrinsic projects a LiDAR point
exactly as P2 . R0_rect . Tr_velo_to_cam does.
"""

from __future__ import annotations

import io
import json
import random
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from detmatch.constants import (
    LABEL_STUDIO_LOCAL_FILES,
    REVIEW_CLASSES,
    REVIEW_FORMATS,
    REVIEW_SELECTIONS,
)
from detmatch.data.kitti import read_calib
from detmatch.files import atomic_write_bytes
from detmatch.structures import Calibration
from serving.store_export import NAMESPACE_SEPARATOR, Store, list_frames, read_frame
from serving.store_layout import FRAME_FILES, StoredFrame

DATUMARO_FORMAT = {"cvat-3d": "sly_pointcloud", "kitti-raw": "kitti_raw",
                   "datumaro-3d": "datumaro"}  # fmt: skip
ROUNDING_DIGITS = 6
MANIFEST = "review.json"
CVAT_LABELS = "cvat_labels.json"  # the CVAT task's label specification


@dataclass(frozen=True)
class Selected:
    record: StoredFrame
    labels: dict[str, Any]  # the stored labels/ID.json
    reason: str


@dataclass(frozen=True)
class ReviewExport:
    format: str
    frames: int
    labels: int
    out: Path


def check_format(format: str) -> None:
    """ValueError naming the formats unless format is one of them (export and import)."""
    if format not in REVIEW_FORMATS:
        raise ValueError(f"--format {format!r}: choose from {', '.join(REVIEW_FORMATS)}")


def item_id(record: StoredFrame) -> str:
    """A frame's id in a review set: NAMESPACE__ID, unique across namespaces, and what an
    import maps back to the stored key."""
    return f"{record.namespace}{NAMESPACE_SEPARATOR}{record.frame_id}"


def select_frames(
    store: Store,
    select: str = "all",
    budget: int | None = None,
    seed: int = 0,
    namespace: str | None = None,
    version: str | None = None,
) -> list[Selected]:
    """The frames to review, in the order a reviewer should see them (see the module
    docstring)."""
    if select not in REVIEW_SELECTIONS:
        raise ValueError(f"--select {select!r}: choose from {', '.join(REVIEW_SELECTIONS)}")
    if select != "all" and (budget is None or budget < 1):
        raise ValueError(f"--select {select} needs --budget N (N >= 1)")
    records = [
        r for r in list_frames(store, namespace) if version is None or r.model_version == version
    ]
    if not records:
        raise ValueError(f"no stored frame matches (store {store}, namespace {namespace}, "
                         f"version {version})")  # fmt: skip
    if select == "random":
        records = sorted(random.Random(seed).sample(records, min(budget, len(records))),
                         key=lambda r: r.key)  # fmt: skip
        return [Selected(r, _labels(store, r), f"random audit sample (seed {seed})")
                for r in records]  # fmt: skip
    chosen = [Selected(r, _labels(store, r), "") for r in records]
    if select == "all":
        return [Selected(s.record, s.labels, "every frame of the filters") for s in chosen]
    rank = disagreement if select == "disagreement" else low_confidence
    ranked = sorted(((rank(s.labels), s) for s in chosen),
                    key=lambda pair: (-pair[0][0], pair[1].record.key))  # fmt: skip
    return [Selected(s.record, s.labels, reason) for (_, reason), s in ranked[:budget]]


def low_confidence(labels: dict[str, Any]) -> tuple[float, str]:
    """A single-modality ranking, what a 3D auto-labeler alone can do: 1 - the mean 3D score
    of the frame's labels (0 for a frame without labels)."""
    scores = [label["score_3d"] for label in labels["labels"]]
    mean = float(np.mean(scores)) if scores else 1.0
    return 1.0 - mean, f"mean 3D score {mean:.3f} of {len(scores)} labels"


def disagreement(labels: dict[str, Any]) -> tuple[float, str]:
    """Where the two teachers disagree, so the labels are most likely wrong: labels the camera
    did not confirm (LiDAR-only labels, inside the camera's view or outside it), matched pairs
    whose classes differ, and matched pairs whose matching cost is over half of tau_hung
    (boxes that barely agree). The score is their count; 2D detections no label took (the
    camera saw something the labels lack) break ties. The reason names each count."""
    records = labels["labels"]
    tau_hung = labels["thresholds"].get("tau_hung") or 1.0
    counts = {
        "unconfirmed LiDAR-only labels in view": sum(
            r["provenance"] == "lidar_only_confident" for r in records
        ),
        "LiDAR-only labels outside the camera's view": sum(
            r["provenance"] == "lidar_only_outside_view" for r in records
        ),
        "class disagreements": sum(
            r["provenance"] == "matched" and r["class_2d"] != r["class_3d"] for r in records
        ),
        "weak matches": sum(
            r["provenance"] == "matched" and r["cost"] > tau_hung / 2 for r in records
        ),
    }
    camera_only = len(labels.get("unmatched_2d", []))
    reason = [f"{n} {what}" for what, n in counts.items() if n]
    reason += [f"{camera_only} camera-only detections"] if camera_only else []
    return float(sum(counts.values())) + min(camera_only, 999) / 1000, (
        ", ".join(reason) or "no disagreement"
    )


def _labels(store: Store, record: StoredFrame) -> dict[str, Any]:
    _, contents = read_frame(store, record, kinds=("labels",))
    (data,) = contents.values()
    return json.loads(data)


def export_review(
    store: Store,
    out: str | Path,
    format: str,
    selected: list[Selected],
    image_url_prefix: str = LABEL_STUDIO_LOCAL_FILES,
) -> ReviewExport:
    """Write the selected frames for review in `format` under out (see the module docstring),
    with out/review.json listing each frame's id, key, model version and reason."""
    check_format(format)
    out = Path(out)
    frames = [_frame(store, s) for s in selected]
    if format == "label-studio":
        labels = _label_studio(frames, out, image_url_prefix)
    else:
        labels = _cvat(frames, out, DATUMARO_FORMAT[format])
    manifest = {
        "format": format,
        "frames": [{"id": f.id, "namespace": f.selected.record.namespace,
                    "frame_id": f.selected.record.frame_id,
                    "model_version": f.selected.record.model_version,
                    "reason": f.selected.reason} for f in frames],
    }  # fmt: skip
    atomic_write_bytes(out / MANIFEST, (json.dumps(manifest, indent=2) + "\n").encode())
    return ReviewExport(format, len(frames), labels, out)


@dataclass(frozen=True)
class _Frame:
    id: str
    selected: Selected
    image_png: bytes
    points: np.ndarray
    calib: Calibration


def _frame(store: Store, selected: Selected) -> _Frame:
    record, contents = read_frame(store, selected.record)

    def content(kind: str) -> bytes:
        directory, suffix = FRAME_FILES[kind]
        return next(v for k, v in contents.items()
                    if k.endswith(f"{directory}/{record.frame_id}{suffix}"))  # fmt: skip

    points = np.frombuffer(content("points"), dtype="<f4").reshape(-1, 4)
    return _Frame(item_id(record), selected, content("image"), points, calib_of(content("calib")))


def calib_of(data: bytes) -> Calibration:
    """A stored KITTI calib file's bytes -> its Calibration (KITTI's own reader)."""
    with tempfile.NamedTemporaryFile("wb", suffix=".txt") as handle:
        handle.write(data)
        handle.flush()
        return read_calib(handle.name)


def camera_matrices(calib: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(intrinsic 3 x 3, extrinsic 3 x 4 LiDAR -> camera 2) with K . E = P2 . R0 . Tr."""
    intrinsic = calib.P2[:, :3]
    rectify, velo = np.eye(4), np.eye(4)
    rectify[:3, :3] = calib.R0_rect
    velo[:3, :] = calib.Tr_velo_to_cam
    extrinsic = np.linalg.solve(intrinsic, calib.P2 @ rectify @ velo)
    return intrinsic, extrinsic


def write_pcd(path: Path, points: np.ndarray) -> None:
    """A binary PCD 0.7 file of (N, 4) x y z intensity float32 (what CVAT uploads)."""
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\n"
        "SIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
        "DATA binary\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode() + np.ascontiguousarray(points, dtype="<f4").tobytes())


def _attributes(label: dict[str, Any], version: str) -> dict[str, Any]:
    return {
        "provenance": label["provenance"],
        "score_3d": round(float(label["score_3d"]), 4),
        "score_2d": -1.0 if label["score_2d"] is None else round(float(label["score_2d"]), 4),
        "cost": -1.0 if label["cost"] is None else round(float(label["cost"]), 4),
        "model_version": version,
    }


def _cvat(frames: list[_Frame], out: Path, datumaro_format: str) -> int:
    try:
        import datumaro as dm
        from datumaro.components import annotation
        from datumaro.components.media import Image as DmImage
        from datumaro.components.media import PointCloud
    except ImportError:
        raise ValueError(
            "CVAT's formats are written with datumaro: pip install 'detmatch[review]'"
        ) from None
    annotation.COORDINATE_ROUNDING_DIGITS = ROUNDING_DIGITS
    present = {lb["class_3d"] for f in frames for lb in f.selected.labels["labels"]}
    classes = sorted(set(REVIEW_CLASSES) | present)
    items, count = [], 0
    with tempfile.TemporaryDirectory(prefix="detmatch-review-") as scratch:
        for index, frame in enumerate(frames):
            pcd, png = Path(scratch) / f"{frame.id}.pcd", Path(scratch) / f"{frame.id}.png"
            write_pcd(pcd, frame.points)
            png.write_bytes(frame.image_png)
            cuboids = []
            for label in frame.selected.labels["labels"]:
                x, y, z, length, width, height, yaw = label["box_3d"]
                cuboids.append(annotation.Cuboid3d(
                    position=[x, y, z], rotation=[0.0, 0.0, yaw],
                    scale=[length, width, height], label=classes.index(label["class_3d"]),
                    id=count, attributes={**_attributes(label, frame.selected.record
                                                        .model_version), "track_id": count},
                ))  # fmt: skip
                count += 1
            items.append(dm.DatasetItem(
                id=frame.id, annotations=cuboids, attributes={"frame": index},
                media=PointCloud.from_file(path=str(pcd),
                                           extra_images=[DmImage.from_file(path=str(png))]),
            ))  # fmt: skip
        dataset = dm.Dataset.from_iterable(
            items, categories=classes, media_type=PointCloud
        )  # fmt: skip
        options = {"allow_undeclared_attrs": True} if datumaro_format == "sly_pointcloud" else {}
        dataset.export(str(out), datumaro_format, save_media=True, **options)
    if datumaro_format == "sly_pointcloud":
        for frame in frames:
            _write_camera(out, frame)
    atomic_write_bytes(out / CVAT_LABELS, (json.dumps(cvat_labels(classes), indent=2) + "\n")
                       .encode())  # fmt: skip
    return count


def cvat_labels(classes: list[str]) -> list[dict[str, Any]]:
    """The labels of a CVAT 3D task for this export (`cvat-cli task create --labels FILE`):
    cuboids of each class, with the attributes every exported cuboid carries (text, so that
    CVAT keeps their values as written)."""
    names = [*_attributes({"provenance": "", "score_3d": 0, "score_2d": None, "cost": None},
                          "").keys(), "track_id"]  # fmt: skip
    return [{"name": name, "type": "cuboid",
             "attributes": [{"name": attribute, "mutable": False, "input_type": "text",
                             "default_value": "", "values": [""]} for attribute in names]}
            for name in classes]  # fmt: skip


def _write_camera(out: Path, frame: _Frame) -> None:
    """The related image's calibration JSON, which datumaro leaves at zeros."""
    directory = out / "ds0" / "related_images" / f"{frame.id}_pcd"
    (image,) = [p for p in directory.iterdir() if p.suffix.lower() != ".json"]
    intrinsic, extrinsic = camera_matrices(frame.calib)
    height, width = Image.open(io.BytesIO(frame.image_png)).size[::-1]
    meta = {
        "name": image.name,
        "meta": {
            "deviceId": "CAM_2",
            "sensorsData": {
                "extrinsicMatrix": [round(float(v), 9) for v in extrinsic.reshape(-1)],
                "intrinsicMatrix": [round(float(v), 9) for v in intrinsic.reshape(-1)],
            },
            "width": width,
            "height": height,
        },
    }
    atomic_write_bytes(image.with_name(image.name + ".json"), json.dumps(meta, indent=2).encode())


def label_studio_config(classes: list[str]) -> str:
    """The labeling interface for the exported tasks: boxes of the product's classes."""
    labels = "\n".join(f'    <Label value="{name}"/>' for name in classes)
    return (
        '<View>\n  <Image name="image" value="$image"/>\n'
        f'  <RectangleLabels name="label" toName="image">\n{labels}\n'
        "  </RectangleLabels>\n</View>\n"
    )


def rectangle_result(
    result_id: str,
    box: list[float],
    class_name: str,
    score: float,
    image_size: tuple[int, int],
    attributes: dict[str, Any] | None = None,
    from_name: str = "label",
    to_name: str = "image",
) -> dict[str, Any]:
    """One box (x1, y1, x2, y2 pixels) as a Label Studio `rectanglelabels` result (percent of
    the image), with its attributes as the region's meta text."""
    width, height = image_size
    x1, y1, x2, y2 = (float(v) for v in box)
    result = {
        "id": result_id, "type": "rectanglelabels", "from_name": from_name, "to_name": to_name,
        "original_width": width, "original_height": height, "image_rotation": 0,
        "value": {"x": 100 * x1 / width, "y": 100 * y1 / height,
                  "width": 100 * (x2 - x1) / width, "height": 100 * (y2 - y1) / height,
                  "rotation": 0, "rectanglelabels": [class_name]},
        "score": float(score),
    }  # fmt: skip
    if attributes is not None:
        result["meta"] = {"text": [json.dumps(attributes)]}
    return result


def drawable(box) -> bool:
    """Whether a 2D box (x1, y1, x2, y2 pixels) has an area: Label Studio cannot draw an
    empty one, and `detmatch review import` refuses it."""
    x1, y1, x2, y2 = (float(v) for v in box)
    return x2 > x1 and y2 > y1


def _label_studio(frames: list[_Frame], out: Path, prefix: str) -> int:
    tasks, count = [], 0
    classes = sorted(set(REVIEW_CLASSES) | {lb["class_2d"] for f in frames
                                            for lb in f.selected.labels["labels"]
                                            if lb["class_2d"] is not None})  # fmt: skip
    for frame in frames:
        relative = f"images/{frame.id}.png"
        atomic_write_bytes(out / relative, frame.image_png)
        width, height = Image.open(io.BytesIO(frame.image_png)).size
        results, scores = [], []
        for index, label in enumerate(frame.selected.labels["labels"]):
            if label["box_2d"] is None or not drawable(label["box_2d"]):
                continue  # no 2D box, or an empty one (a degenerate detection): nothing to draw
            results.append(
                rectangle_result(
                    f"{frame.id}-{index}",
                    label["box_2d"],
                    label["class_2d"],
                    label["score_2d"],
                    (width, height),
                    _attributes(label, frame.selected.record.model_version),
                )
            )
            scores.append(float(label["score_2d"]))
            count += 1
        record = frame.selected.record
        tasks.append({
            "data": {"image": f"{prefix}{relative}", "frame": frame.id,
                     "namespace": record.namespace, "frame_id": record.frame_id,
                     "reason": frame.selected.reason},
            "predictions": [{"model_version": record.model_version,
                             "score": float(np.mean(scores)) if scores else 0.0,
                             "result": results}],
        })  # fmt: skip
    atomic_write_bytes(out / "tasks.json", (json.dumps(tasks, indent=2) + "\n").encode())
    atomic_write_bytes(out / "label_config.xml", label_studio_config(classes).encode())
    return count
