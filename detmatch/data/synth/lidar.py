"""The LiDAR sweep: 64 beams x a full turn of azimuth columns, ray cast against the scene.

A primitive is tested only against the beams and columns of its azimuth / elevation window.
Returns get range noise, random dropout (more for glass, foliage, grazing incidence and long
range) and an intensity from the surface's material. Sparser returns with distance follow
from the fixed angular resolution.
"""

from __future__ import annotations

import numpy as np

from detmatch.data.synth import materials as mat
from detmatch.data.synth.primitives import (
    Primitives,
    cast_pairs,
    nearest_hits,
    surface_at,
    window_pairs,
)
from detmatch.data.synth.scene import Scene
from detmatch.data.synth.sensors import GROUND_Z, LidarModel
from detmatch.data.synth.textures import NoiseTiles, road_surface
from detmatch.data.synth.world import DEFAULT_WORLD, WORLDS, World

BEAM_DIVERGENCE = 0.002  # radians: a return's footprint is range x this
ANGLE_MARGIN = 0.004  # radians added around each window


def lidar_windows(lidar: LidarModel, prims: Primitives) -> np.ndarray:
    """(P, 4) half-open windows row0, row1, col0, col1 of the beam grid (columns may leave
    [0, columns): they wrap around)."""
    corners = prims.bounding_corners()
    centre = prims.center
    azimuth = np.arctan2(corners[..., 1], corners[..., 0])
    centre_azimuth = np.arctan2(centre[:, 1], centre[:, 0])
    relative = np.mod(azimuth - centre_azimuth[:, None] + np.pi, 2 * np.pi) - np.pi
    az_low = centre_azimuth + relative.min(axis=1) - ANGLE_MARGIN
    az_high = centre_azimuth + relative.max(axis=1) + ANGLE_MARGIN

    radius = np.linalg.norm(corners[..., :2] - centre[:, None, :2], axis=2).max(axis=1)
    distance = np.hypot(centre[:, 0], centre[:, 1])
    near = np.maximum(distance - radius, 0.0)
    far = distance + radius
    around = near <= 0.05  # the sensor is inside the footprint's circle: all directions
    z_low, z_high = corners[..., 2].min(axis=1), corners[..., 2].max(axis=1)
    with np.errstate(divide="ignore"):
        el_high = np.arctan2(z_high, np.where(z_high > 0, near, far)) + ANGLE_MARGIN
        el_low = np.arctan2(z_low, np.where(z_low < 0, near, far)) - ANGLE_MARGIN
    full_turn = around | (az_high - az_low > 1.9 * np.pi)

    step = lidar.azimuth_step
    col0 = np.floor((np.pi - az_high) / step - 0.5).astype(np.int64)
    col1 = np.ceil((np.pi - az_low) / step - 0.5).astype(np.int64) + 1
    col0[full_turn], col1[full_turn] = 0, lidar.columns
    descending = lidar.elevations
    row0 = np.searchsorted(-descending, -el_high, side="left")
    row1 = np.searchsorted(-descending, -el_low, side="right")
    row0[around], row1[around] = 0, len(descending)
    return np.stack([row0, row1, col0, col1], axis=1)


def lidar_sweep(
    scene: Scene, lidar: LidarModel, noise: NoiseTiles, world: World = WORLDS[DEFAULT_WORLD]
) -> np.ndarray:
    """Ray cast one sweep. Returns (N, 4) float32 x, y, z, intensity in the LiDAR frame; the
    world's per-material reflectivity overrides and extra dropout apply."""
    prims = scene.primitives
    rng = np.random.default_rng([scene.texture_seed, 2])
    dirs = lidar.directions()
    num_rays = len(dirs)
    origin = np.zeros(3)
    ray, prim = window_pairs(lidar_windows(lidar, prims), lidar.columns, wrap_columns=True)
    hits = cast_pairs(prims, origin, dirs, ray, prim, lidar.max_range)
    t_object, prim_object = nearest_hits(hits, num_rays)
    with np.errstate(divide="ignore"):
        t_ground = np.where(dirs[:, 2] < -1e-6, GROUND_Z / dirs[:, 2], np.inf)
    on_object = t_object < t_ground
    t = np.minimum(t_object, t_ground)
    returned = t <= lidar.max_range

    reflectivity = np.zeros(num_rays)
    dropout = np.zeros(num_rays)
    incidence = np.zeros(num_rays)
    rays = np.flatnonzero(returned & on_object)
    _, unit_point, normal = surface_at(prims, origin, dirs, rays, prim_object[rays])
    material = prims.material[prim_object[rays]]
    region = mat.surface_regions(material, unit_point, prims.half_size[prim_object[rays]])
    reflectivity[rays], dropout[rays] = mat.reflectivity_and_dropout(material, region)
    for material_id, value in world.lidar_reflectivity.items():
        reflectivity[rays[(material == material_id) & (region == mat.BASE)]] = value
    for material_id, extra in world.lidar_dropout.items():
        dropout[rays[material == material_id]] += extra
    incidence[rays] = np.abs(np.einsum("ki,ki->k", normal, dirs[rays]))

    rays = np.flatnonzero(returned & ~on_object)
    ground = t[rays, None] * dirs[rays]
    footprint = t[rays] * BEAM_DIVERGENCE
    _, reflectivity[rays] = road_surface(
        scene.road,
        ground[:, 0],
        ground[:, 1],
        footprint,
        footprint / np.maximum(-dirs[rays, 2], 1e-3),
        noise,
    )
    incidence[rays] = -dirs[rays, 2]

    ranges = np.where(returned, t, 0.0) / lidar.max_range
    lost = lidar.dropout + dropout + 0.35 * ranges**2 + np.where(incidence < 0.06, 0.5, 0.0)
    keep = returned & (rng.random(num_rays) >= lost)
    measured = t + rng.normal(0.0, lidar.range_noise, num_rays)
    strength = reflectivity * (0.7 + 0.3 * incidence) * rng.normal(1.0, 0.1, num_rays)
    intensity = np.round(np.clip(strength, 0.0, 0.99), 2)
    keep_rays = np.flatnonzero(keep)
    points = dirs[keep_rays] * measured[keep_rays, None]
    return np.concatenate([points, intensity[keep_rays, None]], axis=1).astype(np.float32)
