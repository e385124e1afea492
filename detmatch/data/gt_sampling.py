"""Ground-truth database sampling for the 3D detector (SECOND's augmentation, as OpenPCDet and
mmdetection3d do it): objects of other labeled frames, with their LiDAR points, pasted into a
frame's cloud where they were recorded.

The database holds the labeled split's objects only (never unlabeled, dev or val frames), each
with the points inside its box and, optionally, its image crop: the synthetic rig (as KITTI's)
is the same in every frame, so an object pasted where it was recorded can be pasted into the
image at its 2D box as well, and both detectors see it (the 2D targets gain it then).

A frame is filled up to a per-class count: candidates are drawn at random, a candidate whose
bird's-eye-view box overlaps an existing or an accepted box is dropped, the frame's own points
inside the accepted boxes are removed and the objects' points added. Without images the pasted
objects join the 3D targets only: the image and the 2D targets are untouched. With images, an
object whose 2D box would touch another, or that has no pixels (its 2D box rounds to nothing),
is pasted into the cloud only, without its crop: the cloud gets the same objects either way.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from detmatch.data.kitti import KittiDataset
from detmatch.geometry import pairwise_intersection_2d, pairwise_iou_bev, points_in_boxes


@dataclass(frozen=True)
class DatabaseObject:
    """One labeled object: its frame, class id, box (7,) LiDAR frame and points (K, 4); with
    images, its annotated 2D box (4,) original pixels and the image inside it (h, w, 3)."""

    frame_id: str
    class_id: int
    box: np.ndarray
    points: np.ndarray
    box_2d: np.ndarray | None = None
    crop: np.ndarray | None = None


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
        with_images: bool = False,
    ) -> GroundTruthDatabase:
        """The objects of the training classes in frames `ids` with at least min_points
        points inside their box (with_images: and their image crops)."""
        objects = []
        for frame_id in tqdm(ids, desc="ground-truth database", disable=not progress):
            frame = kitti.load_frame(frame_id)
            labels = frame.labels
            if labels is None:
                raise ValueError(f"frame {frame_id} has no labels; the database needs labels")
            keep = np.array([str(n) in classes for n in labels.names], dtype=bool)
            boxes, boxes_2d = labels.boxes_3d.data[keep], labels.boxes_2d.xyxy[keep]
            names = labels.names[keep]
            inside = points_in_boxes(frame.points, boxes)
            for box, box_2d, name, mask in zip(boxes, boxes_2d, names, inside, strict=True):
                if mask.sum() < max(min_points, 1):
                    continue
                crop = None
                if with_images:  # no pixels: no crop, the object still goes into clouds
                    x1, y1, x2, y2 = np.round(box_2d).astype(int)
                    crop = frame.image[max(y1, 0) : y2, max(x1, 0) : x2].copy()
                    crop = crop if crop.size else None
                objects.append(
                    DatabaseObject(
                        frame_id, classes.index(str(name)), box.copy(),
                        frame.points[mask].astype(np.float32),
                        box_2d.copy() if with_images else None, crop,
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
        boxes_2d: np.ndarray | None = None,
    ) -> list[DatabaseObject]:
        """Objects to paste into a frame holding boxes (N, 7) of classes (N,): per class up to
        counts[c] objects in all, from other frames, none overlapping in bird's-eye view.
        boxes_2d (M, 4), when the objects' image crops are pasted too: every 2D box of the
        frame (its DontCare regions included); a candidate without a crop, or whose 2D box
        touches one of them or an accepted crop, keeps no crop (no paste hides or cuts another
        object) and is pasted into the cloud only, so the 3D detector gets the same objects
        with images or without (dropping them cost seed 1 5.1 dev 3D mAP, BENCHMARKS.md)."""
        accepted: list[DatabaseObject] = []
        occupied = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        occupied_2d = None if boxes_2d is None else np.asarray(boxes_2d).reshape(-1, 4)
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
                if occupied_2d is not None and candidate.crop is not None:
                    box_2d = candidate.box_2d[None]
                    if len(occupied_2d) and pairwise_intersection_2d(box_2d, occupied_2d).max() > 0:
                        candidate = dataclasses.replace(candidate, crop=None)
                    else:
                        occupied_2d = np.concatenate([occupied_2d, box_2d])
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


def paste_crops(image: np.ndarray, objects: list[DatabaseObject]) -> np.ndarray:
    """A copy of the (H, W, 3) image with each object's crop written at its 2D box (the rig
    and its calibration are the same for every frame, so the place matches the 3D paste)."""
    pasted = image.copy()
    for obj in objects:
        x1, y1 = np.round(obj.box_2d[:2]).astype(int).clip(0, None)
        h = min(obj.crop.shape[0], image.shape[0] - y1)
        w = min(obj.crop.shape[1], image.shape[1] - x1)
        pasted[y1 : y1 + h, x1 : x1 + w] = obj.crop[:h, :w]
    return pasted
