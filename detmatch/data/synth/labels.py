"""KITTI-style labels from the scene and the rendered visibility.

Rules (all image sizes in full-resolution pixels, scaled for other resolutions):
- An object gets a row when at least 16 full-resolution pixels of it (4 at half resolution)
  are visible; objects outside the image or hidden behind others get none.
- 2D box: tight box of the full (unoccluded) silhouette clipped to the image: from the outer
  edges of its extreme pixels (pixel centres sit at integer coordinates), clipped to
  [0, W - 1] x [0, H - 1] like project_boxes_to_image.
- truncation: fraction of the unclipped silhouette outside the image.
- occlusion: visible / full silhouette pixels >= 0.8 -> 0 (fully visible), >= 0.4 -> 1
  (partly occluded), else 2 (largely occluded).
- DontCare (2D box only): depth beyond 70 m, visible height under 10 px, or less than 5 % of
  the silhouette visible. Its 2D box is the tight box of the visible pixels (the region where
  an unlabelled object shows); it carries truncation -1, occlusion -1, alpha -10.
"""

from __future__ import annotations

import numpy as np

from detmatch.data.synth.camera import Visibility
from detmatch.data.synth.scene import Scene
from detmatch.data.synth.sensors import CameraModel
from detmatch.geometry import observation_angle
from detmatch.structures import Boxes2D, Boxes3D, Labels

FULLY_VISIBLE = 0.8
PARTLY_OCCLUDED = 0.4
MAX_LABEL_DEPTH = 70.0
MIN_VISIBLE_HEIGHT = 10.0
MIN_VISIBLE_FRACTION = 0.05
MIN_VISIBLE_PIXELS = 16.0


def _pixel_extent(boxes: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(N, 4) extreme pixel centres -> (N, 4) xyxy of the pixels' outer edges, clipped."""
    grown = boxes + np.array([-0.5, -0.5, 0.5, 0.5])
    grown[:, 0::2] = np.clip(grown[:, 0::2], 0, camera.width - 1)
    grown[:, 1::2] = np.clip(grown[:, 1::2], 0, camera.height - 1)
    return grown


def occlusion_level(visible_fraction: np.ndarray) -> np.ndarray:
    """(N,) visible / full silhouette pixels -> (N,) KITTI occlusion levels 0, 1, 2."""
    return np.where(
        visible_fraction >= FULLY_VISIBLE, 0, np.where(visible_fraction >= PARTLY_OCCLUDED, 1, 2)
    ).astype(np.int64)


def make_labels(scene: Scene, camera: CameraModel, visibility: Visibility) -> Labels:
    """Rows for every labelled object in view: KITTI classes first (scene order), then
    DontCare rows."""
    min_pixels = MIN_VISIBLE_PIXELS * camera.scale**2
    index = np.array(
        [
            i
            for i, o in enumerate(scene.objects)
            if o.labelled and visibility.visible_pixels[i] >= min_pixels
        ],
        dtype=np.int64,
    )
    if index.size == 0:
        return Labels.empty()
    names = np.array([scene.objects[i].kind for i in index], dtype=object)
    boxes_3d = np.array([scene.objects[i].box for i in index]).reshape(-1, 7)
    boxes_2d = _pixel_extent(visibility.full_box[index], camera)
    fraction = visibility.visible_pixels[index] / visibility.full_pixels[index]
    visible_height = np.nan_to_num(
        visibility.visible_box[index, 3] - visibility.visible_box[index, 1], nan=-1.0
    )
    _, depth = camera.project(boxes_3d[:, :3])
    dont_care = (
        (depth > MAX_LABEL_DEPTH)
        | (visible_height + 1 < MIN_VISIBLE_HEIGHT * camera.scale)
        | (fraction < MIN_VISIBLE_FRACTION)
    )
    alpha = observation_angle(boxes_3d, camera.calib)
    truncated = np.round(visibility.truncation[index], 2)
    occluded = occlusion_level(fraction)
    names[dont_care] = "DontCare"
    boxes_2d[dont_care] = _pixel_extent(visibility.visible_box[index[dont_care]], camera)
    truncated[dont_care], occluded[dont_care], alpha[dont_care] = -1.0, -1, -10.0
    boxes_3d[dont_care] = 0.0
    order = np.argsort(dont_care, kind="stable")
    return Labels(
        names=names[order],
        boxes_2d=Boxes2D(boxes_2d[order]),
        boxes_3d=Boxes3D(boxes_3d[order]),
        truncated=truncated[order],
        occluded=occluded[order],
        alpha=alpha[order],
    )
