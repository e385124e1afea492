"""KITTI object-benchmark evaluation: AP (R40 and R11) for 2D box, BEV, 3D and AOS.

Semantics are the official devkit's (evaluate_object.cpp), which kitti-object-eval-python
ports; the matching kernels live in `kitti_stats`. Per class and difficulty:

- difficulties easy / moderate / hard: ground truth with 2D height < 40 / 25 / 25 px,
  occlusion > 0 / 1 / 2 or truncation > 0.15 / 0.3 / 0.5 is ignored (may absorb a match,
  never counts as a miss); detections with 2D height < 40 / 25 / 25 px are ignored;
- neighbour classes (Van for Car, Person_sitting for Pedestrian) are ignored ground truth;
- unmatched detections inside DontCare regions are not false positives (2D box metric);
- a detection matches when IoU > threshold (strict): 0.7 Car, Van, Truck, Tram; 0.5
  Pedestrian, Person_sitting, Cyclist (the devkit has Car / Pedestrian / Cyclist, the Python
  port adds Van / Person_sitting / Truck, Tram is in neither and gets the vehicle value).
  Class names (DontCare too) match case-insensitively; other names are an error;
- precision is sampled at 41 score thresholds chosen for evenly spaced recall, made
  monotone (max over higher recall); R40 averages points 1..40, R11 points 0, 4, ..., 40.
  A class without valid ground truth scores 0.0, and with n <= 40 valid objects perfect
  detections score 100 (n - 1) / 40 in R40, as in the official code (sample-count effect).

Choices where the devkit and the Python port differ, or neither says:

- Geometry is exact: BEV and 3D IoU are exact rotated-box overlaps (`detmatch.geometry`), so
  identical boxes overlap with IoU 1.0 (the devkit clips polygons exactly too). The Python
  port's `rotate_iou_gpu_eval` is a float32 approximation, notably for identical boxes, and
  can move a pair across the threshold. Boxes go to an 'upright' frame
  (`upright_boxes_from_camera`), a pure rotation of the camera frame: no calibration needed.
- Ground truth is too small when its height is < the minimum (devkit), not <= (Python port).
- DontCare regions apply to the 2D box metric (and AOS) only: the devkit's BEV/3D overlap with
  a DontCare row's placeholder box is always 0 and the Python port checks metric 0 only.
- As in both, an ignored (too small) detection of *any* class can absorb a ground-truth box.
- 2D-only results: a result set whose detections all carry KITTI's placeholder 3D fields
  (dimensions -1, location -1000) is evaluated for the 2D box metric only; its JSON has no
  "bev", "3d" or "aos" keys (omitted, not null). AOS is reported only for results with 3D
  boxes and without the placeholder alpha -10 on any detection (the devkit's rule; the port
  looks at the first detection only), so 2D-only results get no AOS even where they fill
  alpha. The table prints a note instead of those rows. A result set with no detections
  at all is treated as a 3D result and scores 0.0 everywhere. In a 3D result set a row with
  placeholder 3D fields overlaps nothing in BEV/3D.
- A missing result file means no detections for that frame (the devkit stops with an error).

Result dict (JSON-ready, AP in percent):
`{class: {"R40": {"bbox": [easy, moderate, hard], "bev": [...], "3d": [...], "aos": [...]},
"R11": {...}}}`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detmatch.data.kitti import KittiFormatError, KittiObjects, read_objects, validate_frame_id
from detmatch.eval.kitti_overlaps import FlatObjects, flatten_objects, frame_overlaps
from detmatch.eval.kitti_stats import (
    NUM_SAMPLE_POINTS,
    precision_recall_counts,
    score_thresholds,
    true_positive_scores,
)

# IoU threshold per class (lower-case name) and the canonical spelling.
MIN_OVERLAP = {"car": 0.7, "van": 0.7, "truck": 0.7, "tram": 0.7,
               "pedestrian": 0.5, "person_sitting": 0.5, "cyclist": 0.5}  # fmt: skip
CLASS_NAMES = {"car": "Car", "van": "Van", "truck": "Truck", "tram": "Tram",
               "pedestrian": "Pedestrian", "person_sitting": "Person_sitting",
               "cyclist": "Cyclist"}  # fmt: skip
NEIGHBOUR_CLASS = {"car": "van", "pedestrian": "person_sitting"}
DIFFICULTIES = ("easy", "moderate", "hard")
MIN_HEIGHT = (40.0, 25.0, 25.0)
MAX_OCCLUSION = (0, 1, 2)
MAX_TRUNCATION = (0.15, 0.3, 0.5)
METRICS = ("bbox", "bev", "3d")
PLACEHOLDER_ALPHA = -10.0


@dataclass(frozen=True)
class KittiCurves:
    """Raw per-threshold statistics of an evaluation.

    classes: canonical names (C,); tp, fp, fn: (C, 3 metrics, 3 difficulties, 41) counts at
    each score threshold (zeros past `num_thresholds`); similarity: (C, 3, 41) summed
    orientation similarity of the 2D box metric's TPs; thresholds: (C, 3, 3, 41) scores;
    num_thresholds: (C, 3, 3); num_valid_gt: (C, 3) evaluated ground truth per difficulty;
    has_3d: BEV / 3D were evaluated; has_aos: AOS was evaluated.
    """

    classes: tuple[str, ...]
    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    similarity: np.ndarray
    thresholds: np.ndarray
    num_thresholds: np.ndarray
    num_valid_gt: np.ndarray
    has_3d: bool
    has_aos: bool

    def precision(self) -> np.ndarray:
        """(C, 3, 3, 41) precision made monotone: p[i] = max(p[i:])."""
        return _monotone(_ratio(self.tp, self.tp + self.fp))

    def orientation(self) -> np.ndarray:
        """(C, 3, 41) orientation similarity / (TP + FP) of the 2D box metric, made monotone."""
        bbox = METRICS.index("bbox")
        return _monotone(_ratio(self.similarity, self.tp[:, bbox] + self.fp[:, bbox]))

    def recall(self) -> np.ndarray:
        """(C, 3, 3, 41) TP / (TP + FN) at each threshold (zeros past `num_thresholds`)."""
        return _ratio(self.tp, self.tp + self.fn)


def canonical_classes(classes: Sequence[str]) -> tuple[str, ...]:
    """Canonical spellings ('car' -> 'Car'), duplicates removed; unknown names raise ValueError."""
    names: list[str] = []
    for name in classes:
        key = str(name).strip().lower()
        if key not in CLASS_NAMES:
            known = ", ".join(CLASS_NAMES.values())
            raise ValueError(f"unknown KITTI class {name!r}; known classes: {known}")
        if CLASS_NAMES[key] not in names:
            names.append(CLASS_NAMES[key])
    if not names:
        raise ValueError("no classes to evaluate")
    return tuple(names)


def average_precision_r40(precision: np.ndarray) -> np.ndarray:
    """(..., 41) monotone precision -> (...) AP in percent over recall 1/40 .. 1."""
    return precision[..., 1:].sum(axis=-1) / 40.0 * 100.0


def average_precision_r11(precision: np.ndarray) -> np.ndarray:
    """(..., 41) monotone precision -> (...) AP in percent over recall 0, 0.1, .., 1."""
    return precision[..., 0::4].sum(axis=-1) / 11.0 * 100.0


def evaluate(
    gt: Sequence[KittiObjects], dt: Sequence[KittiObjects], classes: Sequence[str]
) -> dict:
    """KITTI AP of per-frame detections against per-frame ground truth (same order).

    gt: label rows (DontCare included); dt: result rows with scores. Returns the result dict
    of the module docstring (AP in percent, official IoU thresholds).
    """
    return results_from_curves(evaluate_curves(gt, dt, classes))


@dataclass(frozen=True)
class PreparedSet:
    """Flat rows and overlaps of an evaluation set: the input of the statistics kernels.

    classes: canonical names; gt: ground truth of the classes and their neighbours; dontcare:
    DontCare regions; dt: all detections; overlaps: {"bbox", "bev", "3d"} -> (P,) every
    frame's (num_dt, num_gt) IoU block, at overlap_offsets (F + 1,); has_3d / has_aos: whether
    BEV and 3D / AOS are evaluated (see the module docstring).
    """

    classes: tuple[str, ...]
    gt: FlatObjects
    dontcare: FlatObjects
    dt: FlatObjects
    overlaps: dict[str, np.ndarray]
    overlap_offsets: np.ndarray
    has_3d: bool
    has_aos: bool


def prepare(
    gt: Sequence[KittiObjects], dt: Sequence[KittiObjects], classes: Sequence[str]
) -> PreparedSet:
    """Check, flatten and overlap per-frame ground truth and detections (same frame order)."""
    names = canonical_classes(classes)
    if len(gt) != len(dt):
        raise ValueError(f"{len(gt)} ground-truth frames but {len(dt)} detection frames")
    for index, objects in enumerate(dt):
        if len(objects) and objects.score is None:
            raise ValueError(f"detections of frame {index} have no scores")
    keys = [name.lower() for name in names]
    relevant = set(keys) | {NEIGHBOUR_CLASS[k] for k in keys if k in NEIGHBOUR_CLASS}
    gt_flat, dc_flat, dt_flat = flatten_objects(gt, dt, relevant)
    has_3d = dt_flat.num == 0 or bool(dt_flat.has_3d.any())
    has_aos = has_3d and not bool(np.any(dt_flat.alpha == PLACEHOLDER_ALPHA))
    overlaps, overlap_offsets = frame_overlaps(gt_flat, dt_flat, with_3d=has_3d)
    return PreparedSet(names, gt_flat, dc_flat, dt_flat, overlaps, overlap_offsets, has_3d, has_aos)


def evaluate_curves(
    gt: Sequence[KittiObjects], dt: Sequence[KittiObjects], classes: Sequence[str]
) -> KittiCurves:
    """The per-threshold TP / FP / FN behind `evaluate`."""
    return match_statistics(prepare(gt, dt, classes))


def match_statistics(prepared: PreparedSet) -> KittiCurves:
    """Both matching passes for every class, difficulty and metric of a prepared set."""
    gt, dt, dc = prepared.gt, prepared.dt, prepared.dontcare
    num_classes = len(prepared.classes)
    shape = (num_classes, len(METRICS), len(DIFFICULTIES), NUM_SAMPLE_POINTS)
    tp, fp, fn = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    similarity = np.zeros((num_classes, len(DIFFICULTIES), NUM_SAMPLE_POINTS))
    thresholds = np.zeros(shape)
    num_thresholds = np.zeros(shape[:3], dtype=np.int64)
    num_valid_gt = np.zeros((num_classes, len(DIFFICULTIES)), dtype=np.int64)
    for c, name in enumerate(prepared.classes):
        key = name.lower()
        min_overlap = MIN_OVERLAP[key]
        for d in range(len(DIFFICULTIES)):
            ignored_gt, ignored_dt = _ignore_codes(gt, dt, key, d)
            num_valid_gt[c, d] = int(np.count_nonzero(ignored_gt == 0))
            for m, metric in enumerate(METRICS):
                if metric != "bbox" and not prepared.has_3d:
                    continue
                common = (
                    prepared.overlaps[metric],
                    prepared.overlap_offsets,
                    gt.offsets,
                    dt.offsets,
                )
                scores = true_positive_scores(
                    *common, ignored_gt, ignored_dt, dt.score, min_overlap
                )
                chosen = score_thresholds(scores, max(num_valid_gt[c, d], 1))
                counts = precision_recall_counts(
                    *common, dc.offsets, ignored_gt, ignored_dt, dt.score, gt.alpha, dt.alpha,
                    dt.bbox, dc.bbox, min_overlap, chosen, metric == "bbox",
                )  # fmt: skip
                n = chosen.shape[0]
                num_thresholds[c, m, d] = n
                thresholds[c, m, d, :n] = chosen
                tp[c, m, d, :n], fp[c, m, d, :n], fn[c, m, d, :n] = counts[:, :3].T
                if metric == "bbox":
                    similarity[c, d, :n] = counts[:, 3]
    return KittiCurves(
        classes=prepared.classes, tp=tp, fp=fp, fn=fn, similarity=similarity,
        thresholds=thresholds, num_thresholds=num_thresholds, num_valid_gt=num_valid_gt,
        has_3d=prepared.has_3d, has_aos=prepared.has_aos,
    )  # fmt: skip


def results_from_curves(curves: KittiCurves) -> dict:
    """The JSON-ready AP dict (percent) of the module docstring."""
    precision = curves.precision()
    orientation = curves.orientation()
    results: dict = {}
    for c, name in enumerate(curves.classes):
        per_class: dict = {}
        for label, average in (("R40", average_precision_r40), ("R11", average_precision_r11)):
            table: dict[str, list[float]] = {}
            for m, metric in enumerate(METRICS):
                if metric == "bbox" or curves.has_3d:
                    table[metric] = [float(v) for v in average(precision[c, m])]
            if curves.has_aos:
                table["aos"] = [float(v) for v in average(orientation[c])]
            per_class[label] = table
        results[name] = per_class
    return results


def evaluate_dirs(gt_dir: Path, pred_dir: Path, ids: Sequence[str], classes: Sequence[str]) -> dict:
    """Evaluate KITTI result files `pred_dir/ID.txt` against labels `gt_dir/ID.txt`.

    A missing result file means no detections, but a result directory with no file for any of
    `ids` is an error (a wrong folder would otherwise score 0.00 everywhere); a missing label
    file is an error; malformed files raise KittiFormatError naming the file and line.
    """
    gt_dir, pred_dir = Path(gt_dir), Path(pred_dir)
    canonical_classes(classes)
    for kind, directory in (("ground-truth", gt_dir), ("result", pred_dir)):
        if not directory.is_dir():
            raise FileNotFoundError(f"{kind} directory {directory} does not exist")
    if not ids:
        raise ValueError("no frame ids to evaluate")
    if not any((pred_dir / f"{frame_id}.txt").is_file() for frame_id in ids):
        found = [p.name for p in pred_dir.iterdir() if p.is_dir()][:2]
        hint = f" (it holds the folders {', '.join(found)}: pass one of them)" if found else ""
        raise ValueError(
            f"result directory {pred_dir} has no result file for any of the {len(ids)} frames "
            f"to evaluate, e.g. {ids[0]}.txt{hint}"
        )
    gt: list[KittiObjects] = []
    dt: list[KittiObjects] = []
    for frame_id in ids:
        validate_frame_id(frame_id)
        label_path = gt_dir / f"{frame_id}.txt"
        if not label_path.is_file():
            raise FileNotFoundError(f"no ground-truth label file {label_path} for frame {frame_id}")
        gt.append(read_objects(label_path))
        result_path = pred_dir / f"{frame_id}.txt"
        if not result_path.is_file():
            dt.append(KittiObjects.empty(with_score=True))
            continue
        objects = read_objects(result_path)
        if len(objects) and objects.score is None:
            raise KittiFormatError(result_path, 1, "result lines need 16 fields (score last)")
        dt.append(objects)
    return evaluate(gt, dt, classes)


def format_table(results: dict) -> str:
    """A readable table: one row per class and metric, R40 and R11 for easy / moderate / hard,
    then the moderate R40 mean over classes per metric (the headline numbers)."""
    header = (
        f"{'class':<15}{'metric':<8}{'IoU':>5}  {'R40 easy':>9}{'moderate':>10}{'hard':>8}"
        f"  {'R11 easy':>9}{'moderate':>10}{'hard':>8}"
    )
    lines = ["KITTI object evaluation, AP in %", header, "-" * len(header)]
    means: dict[str, list[float]] = {}
    for name, per_class in results.items():
        iou = MIN_OVERLAP.get(name.lower())
        for metric in (*METRICS, "aos"):
            if metric not in per_class["R40"]:
                continue
            r40, r11 = per_class["R40"][metric], per_class["R11"][metric]
            shown = "" if iou is None else f"{iou:.2f}"
            lines.append(
                f"{name:<15}{metric:<8}{shown:>5}  {r40[0]:9.2f}{r40[1]:10.2f}{r40[2]:8.2f}"
                f"  {r11[0]:9.2f}{r11[1]:10.2f}{r11[2]:8.2f}"
            )
            means.setdefault(metric, []).append(r40[1])
    if not any("bev" in per_class["R40"] for per_class in results.values()):
        lines.append("(2D-only results: no BEV, 3D or AOS numbers)")
    if means:
        summary = ", ".join(f"{m} {np.mean(v):.2f}" for m, v in means.items())
        lines.append(f"mAP moderate R40 over {len(results)} classes: {summary}")
    return "\n".join(lines)


def within_difficulty(
    bbox: np.ndarray, occluded: np.ndarray, truncated: np.ndarray, difficulty: int
) -> np.ndarray:
    """(N,) bool: the ground-truth objects a difficulty (0 easy, 1 moderate, 2 hard) counts:
    2D box height, occlusion and truncation within its limits."""
    height = bbox[:, 3] - bbox[:, 1]
    return (
        (occluded <= MAX_OCCLUSION[difficulty])
        & (truncated <= MAX_TRUNCATION[difficulty])
        & (height >= MIN_HEIGHT[difficulty])
    )


def _ignore_codes(
    gt: FlatObjects, dt: FlatObjects, key: str, difficulty: int
) -> tuple[np.ndarray, np.ndarray]:
    """(N_gt,), (N_dt,) int64 devkit codes for one class and difficulty (see kitti_stats)."""
    too_hard = ~within_difficulty(gt.bbox, gt.occluded, gt.truncated, difficulty)
    same = gt.names == key
    neighbour = gt.names == NEIGHBOUR_CLASS.get(key, "")
    ignored_gt = np.full(gt.num, -1, dtype=np.int64)
    ignored_gt[neighbour | (same & too_hard)] = 1
    ignored_gt[same & ~too_hard] = 0

    dt_height = np.abs(dt.bbox[:, 3] - dt.bbox[:, 1])
    ignored_dt = np.where(dt.names == key, 0, -1).astype(np.int64)
    ignored_dt[dt_height < MIN_HEIGHT[difficulty]] = 1
    return ignored_gt, ignored_dt


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """numerator / denominator, 0 where the denominator is 0 (no detection at a threshold)."""
    return np.where(denominator > 0, numerator / np.where(denominator > 0, denominator, 1), 0.0)


def _monotone(values: np.ndarray) -> np.ndarray:
    """values[..., i] = max(values[..., i:]) over the last axis."""
    return np.maximum.accumulate(values[..., ::-1], axis=-1)[..., ::-1]
