"""The camera image by ray casting with a z-buffer, and each object's rendered visibility.

One ray per pixel through the pixel centre. A primitive is tested only against the pixels of
its projected bounding box (clipped at a near plane). The road is an analytic plane, the sky a
gradient. Every hit of a labelled object's primitives (not only the nearest) makes up its full
silhouette; the nearest hits make up what is visible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detmatch.data.synth.primitives import (
    Primitives,
    cast_pairs,
    nearest_hits,
    surface_at,
    window_pairs,
)
from detmatch.data.synth.scene import Scene
from detmatch.data.synth.sensors import GROUND_Z, CameraModel
from detmatch.data.synth.shading import contact_darkening, ground_shadow, object_colours
from detmatch.data.synth.textures import NoiseTiles, road_surface, sky_colour

NEAR_PLANE = 0.1
MAX_DISTANCE = 2000.0
HAZE_DISTANCE = 450.0
TRUNCATION_SAMPLES = 20_000
_BOX_EDGES = np.array([(i, i ^ bit) for i in range(8) for bit in (1, 2, 4) if not i & bit])


@dataclass(frozen=True)
class Visibility:
    """Rendered visibility of each scene object (N = number of objects; only labelled objects
    are measured, the rest stay zero / NaN).

    full_pixels: (N,) pixels of the whole silhouette inside the image, ignoring occluders;
    full_box: (N, 4) its tight xyxy box in pixel-centre coordinates (NaN when empty);
    visible_pixels, visible_box: the same for the pixels where the object is the nearest
    surface; truncation: (N,) fraction of the unclipped silhouette outside the image.
    """

    full_pixels: np.ndarray
    full_box: np.ndarray
    visible_pixels: np.ndarray
    visible_box: np.ndarray
    truncation: np.ndarray


@dataclass(frozen=True)
class CameraRender:
    """image: (H, W, 3) uint8 RGB; visibility: per object."""

    image: np.ndarray
    visibility: Visibility


def projected_bounds(camera: CameraModel, corners: np.ndarray) -> np.ndarray:
    """(P, 8, 3) convex hull corners (LiDAR frame) -> (P, 4) u0, v0, u1, v1 of the part in
    front of the near plane (NaN where none is)."""
    uv, depth = camera.project(corners)
    front = depth >= NEAR_PLANE
    a, b = corners[:, _BOX_EDGES[:, 0]], corners[:, _BOX_EDGES[:, 1]]
    da, db = depth[:, _BOX_EDGES[:, 0]], depth[:, _BOX_EDGES[:, 1]]
    crossing = (da - NEAR_PLANE) * (db - NEAR_PLANE) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = np.where(crossing, (NEAR_PLANE - da) / (db - da), 0.0)
    crossing_uv, _ = camera.project(a + weight[..., None] * (b - a))
    points = np.concatenate([uv, crossing_uv], axis=1)
    valid = np.concatenate([front, crossing], axis=1)
    low = np.where(valid[..., None], points, np.inf).min(axis=1)
    high = np.where(valid[..., None], points, -np.inf).max(axis=1)
    bounds = np.concatenate([low, high], axis=1)
    bounds[~valid.any(axis=1)] = np.nan
    return bounds


def bounds_to_windows(bounds: np.ndarray, width: int, height: int) -> np.ndarray:
    """(P, 4) image bounds -> (P, 4) half-open pixel windows row0, row1, col0, col1."""
    safe = np.nan_to_num(bounds, nan=-1.0, posinf=1e9, neginf=-1e9)
    col0 = np.clip(np.floor(safe[:, 0]), 0, width)
    col1 = np.clip(np.ceil(safe[:, 2]) + 1, 0, width)
    row0 = np.clip(np.floor(safe[:, 1]), 0, height)
    row1 = np.clip(np.ceil(safe[:, 3]) + 1, 0, height)
    windows = np.stack([row0, row1, col0, col1], axis=1).astype(np.int64)
    windows[np.isnan(bounds).any(axis=1)] = 0
    return windows


def _per_object_boxes(
    owner: np.ndarray, ray: np.ndarray, width: int, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Unique (owner, ray) pixels -> ((count,) pixel counts, (count, 4) xyxy boxes)."""
    pixels = np.bincount(owner, minlength=count).astype(np.int64)
    boxes = np.full((count, 4), np.nan)
    if len(owner):
        rows, cols = ray // width, ray % width
        for column, values, reduce in (
            (0, cols, np.minimum),
            (1, rows, np.minimum),
            (2, cols, np.maximum),
            (3, rows, np.maximum),
        ):
            start = np.inf if reduce is np.minimum else -np.inf
            extreme = np.full(count, start)
            reduce.at(extreme, owner, values.astype(np.float64))
            boxes[:, column] = np.where(pixels > 0, extreme, np.nan)
    return pixels, boxes


def _truncation(
    camera: CameraModel, prims: Primitives, members: np.ndarray, bounds: np.ndarray
) -> float:
    """Fraction of an object's silhouette outside the image, from a grid of rays over its
    unclipped projected bounds (capped at three image sizes)."""
    width, height = camera.width, camera.height
    u0, v0, u1, v1 = bounds
    u0, u1 = max(u0, -width), min(u1, 2 * width)
    v0, v1 = max(v0, -height), min(v1, 2 * height)
    step = max(1.0, np.sqrt((u1 - u0) * (v1 - v0) / TRUNCATION_SAMPLES))
    us, vs = np.meshgrid(np.arange(u0, u1 + step, step), np.arange(v0, v1 + step, step))
    us, vs = us.ravel(), vs.ravel()
    dirs = camera.directions(us, vs)
    ray = np.repeat(np.arange(len(us)), len(members))
    prim = np.tile(members, len(us))
    hits = cast_pairs(prims, camera.origin, dirs, ray, prim, MAX_DISTANCE)
    covered = np.unique(hits.ray)
    if covered.size == 0:
        return 0.0
    inside = (us[covered] >= -0.5) & (us[covered] <= width - 0.5)
    inside &= (vs[covered] >= -0.5) & (vs[covered] <= height - 0.5)
    return float(1.0 - inside.mean())


def measure_visibility(
    scene: Scene,
    camera: CameraModel,
    hits_ray: np.ndarray,
    hits_prim: np.ndarray,
    visible_owner: np.ndarray,
    bounds: np.ndarray,
) -> Visibility:
    """Silhouettes of the labelled objects from all hits, visibility from the nearest ones."""
    prims, width, count = scene.primitives, camera.width, len(scene.objects)
    labelled = np.array([o.labelled for o in scene.objects], dtype=bool)
    owner = prims.owner[hits_prim]
    keep = labelled[owner]
    num_rays = camera.width * camera.height
    key = np.unique(owner[keep] * num_rays + hits_ray[keep])
    full_pixels, full_box = _per_object_boxes(key // num_rays, key % num_rays, width, count)
    seen = visible_owner >= 0
    seen[seen] = labelled[visible_owner[seen]]
    visible_pixels, visible_box = _per_object_boxes(
        visible_owner[seen], np.flatnonzero(seen), width, count
    )

    truncation = np.zeros(count)
    for index in np.flatnonzero(full_pixels > 0):
        members = np.flatnonzero(prims.owner == index)
        member_bounds = bounds[members]
        member_bounds = member_bounds[~np.isnan(member_bounds).any(axis=1)]
        extent = np.array([*member_bounds[:, :2].min(0), *member_bounds[:, 2:].max(0)])
        if (
            extent[0] < -0.5
            or extent[1] < -0.5
            or extent[2] > width - 0.5
            or extent[3] > camera.height - 0.5
        ):
            truncation[index] = _truncation(camera, prims, members, extent)
    return Visibility(full_pixels, full_box, visible_pixels, visible_box, truncation)


def render_camera(scene: Scene, camera: CameraModel, noise: NoiseTiles) -> CameraRender:
    """Ray cast the scene from camera 2. Returns the image and each object's visibility."""
    prims, light = scene.primitives, scene.lighting
    width, height = camera.width, camera.height
    num_rays = width * height
    origin, dirs = camera.origin, camera.pixel_directions()
    bounds = projected_bounds(camera, prims.bounding_corners())
    ray, prim = window_pairs(bounds_to_windows(bounds, width, height), width, wrap_columns=False)
    hits = cast_pairs(prims, origin, dirs, ray, prim, MAX_DISTANCE)
    t_object, prim_object = nearest_hits(hits, num_rays)
    with np.errstate(divide="ignore"):
        t_ground = np.where(dirs[:, 2] < -1e-6, (GROUND_Z - origin[2]) / dirs[:, 2], np.inf)
    t_ground[t_ground > MAX_DISTANCE] = np.inf
    on_object = t_object < t_ground
    on_ground = ~on_object & np.isfinite(t_ground)
    t = np.where(on_object, t_object, t_ground)
    focal = camera.calib.P2[0, 0]
    footprint = np.where(np.isfinite(t), t, MAX_DISTANCE) / focal

    colour = sky_colour(light, dirs, noise)
    rays = np.flatnonzero(on_ground)
    ground = origin + t[rays, None] * dirs[rays]
    along = footprint[rays] / np.maximum(-dirs[rays, 2], 1e-3)
    albedo, _ = road_surface(scene.road, ground[:, 0], ground[:, 1], footprint[rays], along, noise)
    sunlit = ground_shadow(scene, ground[:, 0], ground[:, 1])
    ambient = light.ambient * contact_darkening(scene, ground[:, 0], ground[:, 1])
    colour[rays] = albedo * (ambient + light.sun_strength * light.sun[2] * sunlit)[:, None]

    rays = np.flatnonzero(on_object)
    _, unit_point, normal = surface_at(prims, origin, dirs, rays, prim_object[rays])
    world = origin + t[rays, None] * dirs[rays]
    colour[rays] = object_colours(
        scene, prim_object[rays], unit_point, world, normal, dirs[rays], footprint[rays], noise
    )
    haze = (1.0 - np.exp(-np.where(np.isfinite(t), t, 1e9) / HAZE_DISTANCE))[:, None]
    colour = colour * (1 - haze) + light.sky_horizon * haze

    visible_owner = np.where(on_object, prims.owner[np.maximum(prim_object, 0)], -1)
    visibility = measure_visibility(scene, camera, hits.ray, hits.prim, visible_owner, bounds)
    image = _finish(
        colour.reshape(height, width, 3), np.random.default_rng([scene.texture_seed, 1])
    )
    return CameraRender(image, visibility)


def _finish(colour: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Linear-ish RGB (H, W, 3) -> uint8: slight optical blur, vignetting, sensor noise."""
    padded = np.pad(colour, ((1, 1), (1, 1), (0, 0)), mode="edge")
    blurred = 0.25 * padded[:, :-2] + 0.5 * padded[:, 1:-1] + 0.25 * padded[:, 2:]
    blurred = 0.25 * blurred[:-2] + 0.5 * blurred[1:-1] + 0.25 * blurred[2:]
    height, width = colour.shape[:2]
    yy, xx = np.meshgrid(np.linspace(-1, 1, height), np.linspace(-1, 1, width), indexing="ij")
    vignette = 1.0 - 0.12 * (xx**2 * 0.6 + yy**2 * 0.4)
    noisy = blurred * vignette[..., None] + rng.normal(0.0, 0.012, blurred.shape)
    return np.clip(np.round(noisy * 255.0), 0, 255).astype(np.uint8)
