"""A slow, plain-Python KITTI evaluator written straight from the devkit's description.

Independent of detmatch.eval and detmatch.geometry: its own box overlaps (Sutherland-Hodgman
clipping in the camera's x-z plane), its own ignore rules and matching loops, one frame and
one threshold at a time. Only for small test sets.
"""

from __future__ import annotations

import math

from detmatch.data.kitti import KittiObjects

IOU = {"car": 0.7, "van": 0.7, "truck": 0.7, "tram": 0.7,
       "pedestrian": 0.5, "person_sitting": 0.5, "cyclist": 0.5}  # fmt: skip
NEIGHBOUR = {"car": "van", "pedestrian": "person_sitting"}
MIN_H = [40, 25, 25]
MAX_OCC = [0, 1, 2]
MAX_TRUNC = [0.15, 0.3, 0.5]


def rows(objects: KittiObjects) -> list[dict]:
    out = []
    for i in range(len(objects)):
        h, w, l = (float(v) for v in objects.dimensions[i])
        x, y, z = (float(v) for v in objects.location[i])
        out.append(
            {
                "name": str(objects.names[i]).lower(),
                "trunc": float(objects.truncated[i]),
                "occ": int(objects.occluded[i]),
                "alpha": float(objects.alpha[i]),
                "box": [float(v) for v in objects.bbox[i]],
                "hwl": (h, w, l),
                "xyz": (x, y, z),
                "ry": float(objects.rotation_y[i]),
                "score": 0.0 if objects.score is None else float(objects.score[i]),
                "has_3d": h > 0 and w > 0 and l > 0 and y > -999,
            }
        )
    return out


# ------------------------------------------------------------------------------------ overlaps


def iou_2d(a: list[float], b: list[float]) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def footprint(obj: dict) -> list[tuple[float, float]]:
    """Corners in the camera x-z plane: rotation_y turns the object about the camera y axis."""
    _, w, l = obj["hwl"]
    x, _, z = obj["xyz"]
    c, s = math.cos(obj["ry"]), math.sin(obj["ry"])
    corners = []
    for dx, dz in ((l / 2, w / 2), (l / 2, -w / 2), (-l / 2, -w / 2), (-l / 2, w / 2)):
        corners.append((x + c * dx + s * dz, z - s * dx + c * dz))
    return corners


def polygon_area(points: list[tuple[float, float]]) -> float:
    total = 0.0
    for i in range(len(points)):
        x1, y1 = points[i]
        x2, y2 = points[(i + 1) % len(points)]
        total += x1 * y2 - x2 * y1
    return total / 2


def clip(subject: list, clipper: list) -> list:
    """Sutherland-Hodgman: the part of polygon `subject` inside convex polygon `clipper`."""
    sign = 1.0 if polygon_area(clipper) > 0 else -1.0

    def inside(p, a, b):
        return sign * ((b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])) >= 0

    def crossing(p, q, a, b):
        d1 = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
        d2 = (b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0])
        t = d1 / (d1 - d2)
        return (p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]))

    output = list(subject)
    for i in range(len(clipper)):
        a, b = clipper[i], clipper[(i + 1) % len(clipper)]
        points, output = output, []
        for j in range(len(points)):
            p, q = points[j], points[(j + 1) % len(points)]
            if inside(q, a, b):
                if not inside(p, a, b):
                    output.append(crossing(p, q, a, b))
                output.append(q)
            elif inside(p, a, b):
                output.append(crossing(p, q, a, b))
        if not output:
            return []
    return output


def ground_intersection(a: dict, b: dict) -> float:
    part = clip(footprint(a), footprint(b))
    return abs(polygon_area(part)) if len(part) >= 3 else 0.0


def iou_bev(a: dict, b: dict) -> float:
    inter = ground_intersection(a, b)
    union = a["hwl"][1] * a["hwl"][2] + b["hwl"][1] * b["hwl"][2] - inter
    return inter / union


def iou_3d(a: dict, b: dict) -> float:
    # Camera y points down: a box spans [y - h, y] vertically.
    (ya, ha), (yb, hb) = (a["xyz"][1], a["hwl"][0]), (b["xyz"][1], b["hwl"][0])
    overlap = min(ya, yb) - max(ya - ha, yb - hb)
    inter = ground_intersection(a, b) * max(0.0, overlap)
    volume = a["hwl"][0] * a["hwl"][1] * a["hwl"][2] + b["hwl"][0] * b["hwl"][1] * b["hwl"][2]
    return inter / (volume - inter)


def overlap(metric: str, det: dict, gt: dict) -> float:
    if metric == "bbox":
        return iou_2d(det["box"], gt["box"])
    if not (det["has_3d"] and gt["has_3d"]):
        return 0.0
    return iou_bev(det, gt) if metric == "bev" else iou_3d(det, gt)


# ------------------------------------------------------------------------------ the algorithm


def gt_code(obj: dict, cls: str, d: int) -> int:
    if obj["name"] == cls:
        valid = 1
    elif NEIGHBOUR.get(cls) == obj["name"]:
        valid = 0
    else:
        valid = -1
    height = obj["box"][3] - obj["box"][1]
    too_hard = obj["occ"] > MAX_OCC[d] or obj["trunc"] > MAX_TRUNC[d] or height < MIN_H[d]
    if valid == 1 and not too_hard:
        return 0
    if valid == 0 or (valid == 1 and too_hard):
        return 1
    return -1


def dt_code(obj: dict, cls: str, d: int) -> int:
    if abs(obj["box"][3] - obj["box"][1]) < MIN_H[d]:
        return 1
    return 0 if obj["name"] == cls else -1


def frame_stats(gts, dets, dcs, ig, idt, ov, min_ov, compute_fp, thresh, metric):
    """The devkit's computeStatistics for one frame: (tp, fp, fn, similarity, tp scores)."""
    assigned = [False] * len(dets)
    low = [compute_fp and d["score"] < thresh for d in dets]
    tp = fp = fn = 0
    similarity = 0.0
    scores = []
    for i in range(len(gts)):
        if ig[i] == -1:
            continue
        det, best_score, max_ov, took_ignored = None, None, 0.0, False
        for j in range(len(dets)):
            if idt[j] == -1 or assigned[j] or low[j] or not ov[j][i] > min_ov:
                continue
            if not compute_fp:
                if best_score is None or dets[j]["score"] > best_score:
                    det, best_score = j, dets[j]["score"]
            elif idt[j] == 0 and (ov[j][i] > max_ov or took_ignored):
                det, max_ov, took_ignored = j, ov[j][i], False
            elif idt[j] == 1 and det is None:
                det, took_ignored = j, True
        if det is None:
            fn += ig[i] == 0
        elif ig[i] == 1 or idt[det] == 1:
            assigned[det] = True
        else:
            tp += 1
            scores.append(dets[det]["score"])
            similarity += (1 + math.cos(gts[i]["alpha"] - dets[det]["alpha"])) / 2
            assigned[det] = True
    if compute_fp:
        for j in range(len(dets)):
            if not (assigned[j] or idt[j] != 0 or low[j]):
                fp += 1
        if metric == "bbox":
            for dc in dcs:
                for j in range(len(dets)):
                    if assigned[j] or idt[j] != 0 or low[j]:
                        continue
                    b, r = dets[j]["box"], dc["box"]
                    w = min(b[2], r[2]) - max(b[0], r[0])
                    h = min(b[3], r[3]) - max(b[1], r[1])
                    area = (b[2] - b[0]) * (b[3] - b[1])
                    if w > 0 and h > 0 and w * h / area > min_ov:
                        assigned[j] = True
                        fp -= 1
    return tp, fp, fn, similarity, scores


def thresholds_for(scores: list[float], n_gt: int) -> list[float]:
    v = sorted(scores, reverse=True)
    out, current = [], 0.0
    for i in range(len(v)):
        left = (i + 1) / n_gt
        right = (i + 2) / n_gt if i < len(v) - 1 else left
        if right - current < current - left and i < len(v) - 1:
            continue
        out.append(v[i])
        current += 1 / 40
    return out


def curve(frames, cls: str, d: int, metric: str) -> tuple[list[float], list[float]]:
    """41-point monotone precision and orientation similarity of one class / difficulty."""
    min_ov = IOU[cls]
    prepared, all_scores, n_gt = [], [], 0
    for gt_rows, dt_rows in frames:
        gts = [g for g in gt_rows if g["name"] != "dontcare"]
        dcs = [g for g in gt_rows if g["name"] == "dontcare"]
        ig = [gt_code(g, cls, d) for g in gts]
        idt = [dt_code(x, cls, d) for x in dt_rows]
        ov = [[overlap(metric, x, g) for g in gts] for x in dt_rows]
        n_gt += ig.count(0)
        *_, scores = frame_stats(gts, dt_rows, dcs, ig, idt, ov, min_ov, False, 0.0, metric)
        all_scores += scores
        prepared.append((gts, dt_rows, dcs, ig, idt, ov))
    thresholds = thresholds_for(all_scores, n_gt) if all_scores else []
    precision, orientation = [0.0] * 41, [0.0] * 41
    for t, thresh in enumerate(thresholds):
        tp = fp = 0
        similarity = 0.0
        for gts, dets, dcs, ig, idt, ov in prepared:
            a, b, _, s, _ = frame_stats(gts, dets, dcs, ig, idt, ov, min_ov, True, thresh, metric)
            tp, fp, similarity = tp + a, fp + b, similarity + s
        precision[t] = tp / (tp + fp) if tp + fp else 0.0
        orientation[t] = similarity / (tp + fp) if tp + fp else 0.0
    for i in range(41):
        precision[i] = max(precision[i:])
        orientation[i] = max(orientation[i:])
    return precision, orientation


def reference_evaluate(gt: list[KittiObjects], dt: list[KittiObjects], classes: list[str]) -> dict:
    frames = [(rows(g), rows(x)) for g, x in zip(gt, dt, strict=True)]
    all_dets = [x for _, dets in frames for x in dets]
    with_3d = not all_dets or any(x["has_3d"] for x in all_dets)
    with_aos = with_3d and all(x["alpha"] != -10 for x in all_dets)
    metrics = ["bbox", "bev", "3d"] if with_3d else ["bbox"]
    results = {}
    for name in classes:
        cls = name.lower()
        r40: dict = {}
        r11: dict = {}
        for metric in metrics:
            for d in range(3):
                precision, orientation = curve(frames, cls, d, metric)
                keys = [metric, "aos"] if metric == "bbox" and with_aos else [metric]
                for key, values in zip(keys, (precision, orientation), strict=False):
                    r40.setdefault(key, []).append(sum(values[1:]) / 40 * 100)
                    r11.setdefault(key, []).append(sum(values[0::4]) / 11 * 100)
        order = [k for k in ("bbox", "bev", "3d", "aos") if k in r40]
        results[name] = {"R40": {k: r40[k] for k in order}, "R11": {k: r11[k] for k in order}}
    return results
