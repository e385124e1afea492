"""Ground-truth database sampling for the 3D detector (SECOND's augmentation, as OpenPCDet and
mmdetection3d do it): objects of other labeled frames, with their LiDAR points, pasted into a
frame's cloud where they were recorded.

The database holds the labeled split's objects only (never unlabeled, dev or val frames), each
with the points inside its box. A frame is filled up to a per-class count: candidates are drawn
at random, a candidate whose bird's-eye-view box overlaps an existing or an accepted box is
dropped, the frame's own points inside the accepted boxes are removed and the objects' points
added. The pasted objects join the 3D targets only: the image and the 2D targets are untouched.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from detmatch.data.kitti import KittiDataset
from detmatch.geometry import pairwise_iou_bev, points_in_boxes


@dataclass(frozen=True)
class DatabaseObject:
    """One labeled object: its frame, class id, box (7,) LiDAR frame and points (K, 4)."""

    frame_id: str
    class_id: int
    box: np.ndarray
    points: np.ndarray


class GroundTruthDatabase:
    """Objects of labeled frames by class (class ids of the training classes)."""

    def __init__(self, objects: list[DatabaseObject], num_classes: int) -> None:
        self.objects = objects
        self.by_class = [
            [i for i, o in enumerate(objects) if o.class_id == c] for c in range(num_classes)
        ]

    def __len__(self) -> int:
        return len(self.objects)

    @property
    def frame_ids(self) -> set[str]:
        return {o.frame_id for o in self.objects}

    @staticmethod
    def build(
        kitti: KittiDataset,
        ids: list[str],
        classes: tuple[str, ...],
        min_points: int,
        progress: bool = False,
    ) -> GroundTruthDatabase:
        """The objects of the training classes in frames `ids` with at least min_points
        points inside their box."""
        objects = []
        for frame_id in tqdm(ids, desc="ground-truth database", disable=not progress):
            frame = kitti.load_frame(frame_id)
            labels = frame.labels
            if labels is None:
                raise ValueError(f"frame {frame_id} has no labels; the database needs labels")
            keep = np.array([str(n) in classes for n in labels.names], dtype=bool)
            boxes = labels.boxes_3d.data[keep]
            names = labels.names[keep]
            inside = points_in_boxes(frame.points, boxes)
            for box, name, mask in zip(boxes, names, inside, strict=True):
                if mask.sum() >= max(min_points, 1):
                    objects.append(
                        DatabaseObject(
                            frame_id, classes.index(str(name)), box.copy(),
                            frame.points[mask].astype(np.float32),
                        )
                    )  # fmt: skip
        return GroundTruthDatabase(objects, len(classes))

    def sample(
        self,
        rng: np.random.Generator,
        boxes: np.ndarray,
        classes: np.ndarray,
        counts: tuple[int, ...],
        frame_id: str,
    ) -> list[DatabaseObject]:
        """Objects to paste into a frame holding boxes (N, 7) of classes (N,): per class up to
        counts[c] objects in all, from other frames, none overlapping in bird's-eye view."""
        accepted: list[DatabaseObject] = []
        occupied = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        for class_id, target in enumerate(counts):
            wanted = target - int(np.sum(classes == class_id))
            pool = [i for i in self.by_class[class_id] if self.objects[i].frame_id != frame_id]
            if wanted <= 0 or not pool:
                continue
            chosen = rng.choice(len(pool), size=min(wanted, len(pool)), replace=False)
            for candidate in (self.objects[pool[i]] for i in chosen):
                box = candidate.box[None]
                if len(occupied) and pairwise_iou_bev(box, occupied).max() > 0:
                    continue
                accepted.append(candidate)
                occupied = np.concatenate([occupied, box])
        return accepted


def paste_objects(points: np.ndarray, objects: list[DatabaseObject]) -> np.ndarray:
    """The cloud without its points inside the pasted boxes, plus the objects' points."""
    if not objects:
        return points
    boxes = np.stack([o.box for o in objects])
    inside = points_in_boxes(points, boxes).any(axis=0)
    return np.concatenate([points[~inside], *[o.points for o in objects]]).astype(points.dtype)
