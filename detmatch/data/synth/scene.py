"""What a synthetic scene is: its objects, their primitives, the road layout and the lighting.

Everything is placed in the LiDAR frame (x forward, y left, z up; the road at z = GROUND_Z).
Road coordinates (s along the road, u to its left, metres) place things along the carriageway;
the LiDAR sits at s = 0, u = ego_offset. No two objects' footprints intersect.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detmatch.data.synth.primitives import Primitives

LABELLED_CLASSES = ("Car", "Van", "Pedestrian", "Cyclist")
# KITTI training-set means and spreads: (length, width, height) metres.
CLASS_SIZES = {
    "Car": ((3.88, 1.63, 1.53), (0.40, 0.10, 0.13)),
    "Van": ((5.08, 1.90, 2.21), (0.50, 0.12, 0.25)),
    "Pedestrian": ((0.84, 0.66, 1.76), (0.20, 0.10, 0.11)),
    "Cyclist": ((1.76, 0.60, 1.74), (0.17, 0.10, 0.09)),
}
SIZE_LIMITS = {
    "Car": ((3.2, 1.45, 1.3), (4.9, 1.9, 1.8)),
    "Van": ((4.3, 1.7, 1.85), (5.9, 2.15, 2.6)),
    "Pedestrian": ((0.45, 0.48, 1.5), (1.2, 0.85, 1.98)),
    "Cyclist": ((1.5, 0.45, 1.58), (2.05, 0.8, 1.9)),
}


@dataclass(frozen=True)
class SceneObject:
    """A thing in the scene. kind: a KITTI class (Car, Van, Pedestrian, Cyclist) or an
    unlabelled kind ("clutter/post", "building", "tree", ...); box: (7,) tight LiDAR-frame box;
    round_shadow: its shadow is better drawn as a disc (tree crowns)."""

    kind: str
    box: np.ndarray
    round_shadow: bool = False

    @property
    def labelled(self) -> bool:
        return self.kind in LABELLED_CLASSES

    @property
    def is_clutter(self) -> bool:
        return self.kind.startswith("clutter/")


@dataclass(frozen=True)
class RoadLayout:
    """Straight road. heading: road direction in the LiDAR frame (radians); ego_offset: u of
    the LiDAR; lane_width; road_left / road_right: u of the asphalt edges (incl. parking
    strips); lanes_left / lanes_right: u of the outermost lane lines; sidewalk_left / _right:
    widths beyond the curbs (0 = grass verge)."""

    heading: float
    ego_offset: float
    lane_width: float
    lanes_left: float
    lanes_right: float
    road_left: float
    road_right: float
    sidewalk_left: float
    sidewalk_right: float

    def to_world(self, s: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates -> LiDAR-frame x, y."""
        c, sn = np.cos(self.heading), np.sin(self.heading)
        du = np.asarray(u) - self.ego_offset
        return c * np.asarray(s) - sn * du, sn * np.asarray(s) + c * du

    def to_road(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LiDAR-frame x, y -> road coordinates s, u."""
        c, sn = np.cos(self.heading), np.sin(self.heading)
        return c * x + sn * y, -sn * x + c * y + self.ego_offset


@dataclass(frozen=True)
class Lighting:
    """sun: (3,) unit vector towards the sun (LiDAR frame); ambient, sun strength; sky_top,
    sky_horizon: (3,) RGB in [0, 1]."""

    sun: np.ndarray
    ambient: float
    sun_strength: float
    sky_top: np.ndarray
    sky_horizon: np.ndarray


@dataclass(frozen=True)
class Scene:
    """objects: every thing in the scene; primitives: their shapes (owner indexes objects);
    texture_seed: seeds the procedural textures of the frame."""

    objects: tuple[SceneObject, ...]
    primitives: Primitives
    road: RoadLayout
    lighting: Lighting
    texture_seed: int

    def boxes(self, which: str = "labelled") -> np.ndarray:
        """(N, 7) boxes of the "labelled" objects, the "clutter" or "all"."""
        keep = [
            o.box
            for o in self.objects
            if which == "all"
            or (which == "labelled" and o.labelled)
            or (which == "clutter" and o.is_clutter)
        ]
        return np.array(keep).reshape(-1, 7)


def frame_rng(seed: int, frame_index: int) -> np.random.Generator:
    """The random generator of one frame, independent of every other frame."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(frame_index,)))
