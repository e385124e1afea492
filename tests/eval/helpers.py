"""Builders of KITTI rows and random scenes for the evaluation tests."""

from __future__ import annotations

import numpy as np

from detmatch.data.kitti import KittiObjects

PLACEHOLDER_3D = {"hwl": (-1.0, -1.0, -1.0), "xyz": (-1000.0, -1000.0, -1000.0), "ry": -10.0}
SIZES = {"Car": (1.5, 1.6, 3.9), "Van": (2.2, 1.9, 5.0), "Truck": (3.2, 2.5, 10.0),
         "Pedestrian": (1.75, 0.6, 0.8), "Person_sitting": (1.3, 0.6, 0.9),
         "Cyclist": (1.7, 0.6, 1.8)}  # fmt: skip

TRUNCATIONS = np.array([0.0, 0.1, 0.2, 0.4, 0.6])
WEIGHTS = np.array([0.5, 0.2, 0.15, 0.1, 0.05])


def row(
    name: str,
    box: tuple[float, float, float, float],
    *,
    score: float | None = None,
    trunc: float = 0.0,
    occ: int = 0,
    alpha: float = 0.0,
    hwl: tuple[float, float, float] | None = None,
    xyz: tuple[float, float, float] | None = None,
    ry: float = 0.0,
) -> dict:
    """One KITTI row; by default a real 3D box placed from the 2D box's position."""
    if name == "DontCare":
        return {"name": name, "box": box, "score": score, "trunc": -1.0, "occ": -1,
                "alpha": -10.0, **PLACEHOLDER_3D}  # fmt: skip
    if xyz is None:
        xyz = ((box[0] + box[2]) / 20.0, 1.6, 10.0 + box[1] / 10.0)
    return {"name": name, "box": box, "score": score, "trunc": trunc, "occ": occ,
            "alpha": alpha, "hwl": hwl or SIZES.get(name, (1.5, 1.5, 1.5)), "xyz": xyz,
            "ry": ry}  # fmt: skip


def frame(rows: list[dict], scored: bool | None = None) -> KittiObjects:
    """Rows -> KittiObjects; scored defaults to 'the rows carry scores'."""
    if scored is None:
        scored = bool(rows) and rows[0]["score"] is not None
    if not rows:
        return KittiObjects.empty(with_score=scored)
    return KittiObjects(
        names=np.array([r["name"] for r in rows], dtype=object),
        truncated=np.array([r["trunc"] for r in rows], dtype=np.float64),
        occluded=np.array([r["occ"] for r in rows], dtype=np.int64),
        alpha=np.array([r["alpha"] for r in rows], dtype=np.float64),
        bbox=np.array([r["box"] for r in rows], dtype=np.float64).reshape(-1, 4),
        dimensions=np.array([r["hwl"] for r in rows], dtype=np.float64).reshape(-1, 3),
        location=np.array([r["xyz"] for r in rows], dtype=np.float64).reshape(-1, 3),
        rotation_y=np.array([r["ry"] for r in rows], dtype=np.float64),
        score=np.array([r["score"] for r in rows], dtype=np.float64) if scored else None,
    )


def with_scores(objects: KittiObjects, scores: np.ndarray) -> KittiObjects:
    return KittiObjects(
        names=objects.names, truncated=objects.truncated, occluded=objects.occluded,
        alpha=objects.alpha, bbox=objects.bbox, dimensions=objects.dimensions,
        location=objects.location, rotation_y=objects.rotation_y,
        score=np.asarray(scores, dtype=np.float64),
    )  # fmt: skip


def random_scene(
    rng: np.random.Generator,
    num_frames: int,
    max_objects: int = 7,
    classes: tuple[str, ...] = ("Car", "Van", "Pedestrian", "Person_sitting", "Cyclist", "Truck"),
    easy_only: bool = False,
) -> list[KittiObjects]:
    """Random KITTI-like ground truth (DontCare included unless easy_only)."""
    frames = []
    for _ in range(num_frames):
        rows = []
        for _ in range(rng.integers(0, max_objects + 1)):
            name = str(rng.choice(classes))
            x1, y1 = rng.uniform(0, 700), rng.uniform(100, 200)
            height = rng.uniform(45, 130) if easy_only else rng.uniform(15, 130)
            width = height * rng.uniform(0.4, 2.0)
            h, w, l = np.array(SIZES[name]) * rng.uniform(0.85, 1.15, 3)
            rows.append(
                row(
                    name,
                    (x1, y1, x1 + width, y1 + height),
                    trunc=0.0 if easy_only else float(rng.choice(TRUNCATIONS, p=WEIGHTS)),
                    occ=0 if easy_only else int(rng.choice(4, p=WEIGHTS[:4] / WEIGHTS[:4].sum())),
                    alpha=rng.uniform(-np.pi, np.pi),
                    hwl=(h, w, l),
                    xyz=(rng.uniform(-15, 15), rng.uniform(1.0, 2.0), rng.uniform(4, 45)),
                    ry=rng.uniform(-np.pi, np.pi),
                )
            )
        if not easy_only:
            for _ in range(rng.integers(0, 3)):
                x1, y1 = rng.uniform(0, 1100), rng.uniform(100, 250)
                size = rng.uniform(10, 80)
                rows.append(row("DontCare", (x1, y1, x1 + size, y1 + size * 0.6)))
        frames.append(frame(rows, scored=False))
    return frames


def noisy_detections(
    rng: np.random.Generator, gt: list[KittiObjects], noise: float = 1.0
) -> list[KittiObjects]:
    """Jittered copies of the ground truth (some relabelled, some duplicated, some missed),
    false positives, detections on DontCare regions; scores with ties."""
    frames = []
    names = ("Car", "Pedestrian", "Cyclist", "Van")
    for objects in gt:
        rows = []
        for i in range(len(objects)):
            box = objects.bbox[i]
            if objects.names[i] == "DontCare":
                if rng.random() < 0.5:
                    shrink = rng.uniform(0, 0.3) * (box[2] - box[0])
                    rows.append(_random_row(rng, names, (box[0] + shrink, box[1], box[2], box[3])))
                continue
            for _ in range(1 + int(rng.random() < 0.2) - int(rng.random() < 0.15)):
                name = str(objects.names[i]) if rng.random() < 0.85 else str(rng.choice(names))
                jitter = rng.normal(0, 4 * noise, 4)
                rows.append(
                    row(
                        name,
                        tuple(box + jitter),
                        score=_score(rng),
                        alpha=objects.alpha[i] + rng.normal(0, 0.4),
                        hwl=tuple(objects.dimensions[i] * (1 + rng.normal(0, 0.05 * noise, 3))),
                        xyz=tuple(objects.location[i] + rng.normal(0, 0.12 * noise, 3)),
                        ry=objects.rotation_y[i] + rng.normal(0, 0.1 * noise),
                    )
                )
        for _ in range(rng.integers(0, 3)):
            x1, y1 = rng.uniform(0, 1100), rng.uniform(100, 250)
            height = rng.uniform(15, 100)
            rows.append(_random_row(rng, names, (x1, y1, x1 + height, y1 + height)))
        order = rng.permutation(len(rows))
        frames.append(frame([rows[k] for k in order], scored=True))
    return frames


def _random_row(rng: np.random.Generator, names: tuple[str, ...], box: tuple) -> dict:
    name = str(rng.choice(names))
    return row(
        name,
        tuple(float(v) for v in box),
        score=_score(rng),
        alpha=rng.uniform(-np.pi, np.pi),
        xyz=(rng.uniform(-15, 15), rng.uniform(1.0, 2.0), rng.uniform(4, 45)),
        ry=rng.uniform(-np.pi, np.pi),
    )


def _score(rng: np.random.Generator) -> float:
    # Half the scores on a coarse grid, so that ties occur.
    return float(rng.integers(1, 10) / 10) if rng.random() < 0.5 else float(rng.random())
