"""Camera shading: object colours by material and region, Lambertian sun + sky light, glossy
paint and glass, and the shadows objects cast on the road.
"""

from __future__ import annotations

import numpy as np

from detmatch.data.synth import materials as mat
from detmatch.data.synth.scene import Scene
from detmatch.data.synth.textures import NoiseTiles
from detmatch.geometry import bev_corners

HEADLIGHT = np.array([0.92, 0.92, 0.86])
TAILLIGHT = np.array([0.72, 0.07, 0.06])
PLATE_COLOUR = np.array([0.9, 0.9, 0.86])
GLASS_COLOUR = np.array([0.07, 0.09, 0.12])
WINDOW_COLOUR = np.array([0.20, 0.24, 0.30])
_SHADOW_SLIMMING = {"Pedestrian": (0.55, 0.5), "Cyclist": (0.9, 0.3)}
_ANGLES = np.linspace(0, 2 * np.pi, 12, endpoint=False)
_UNIT_CIRCLE = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=1)


def object_colours(
    scene: Scene,
    prim: np.ndarray,
    unit_point: np.ndarray,
    world_point: np.ndarray,
    normal: np.ndarray,
    view: np.ndarray,
    footprint: np.ndarray,
    noise: NoiseTiles,
) -> np.ndarray:
    """Lit colour of object surface points.

    prim: (K,) primitive hit; unit_point: (K, 3) in its unit space; world_point, normal,
    view: (K, 3) LiDAR-frame point, unit normal and unit direction from the camera;
    footprint: (K,) metres one pixel covers there. Returns (K, 3) RGB, not clipped.
    """
    prims, light = scene.primitives, scene.lighting
    material = prims.material[prim]
    region = mat.surface_regions(material, unit_point, prims.half_size[prim])
    base = prims.colour[prim].copy()
    second = prims.colour2[prim]
    use_second = np.isin(region, (mat.HAIR, mat.ROOF, mat.SECOND)) | (
        (region == mat.SKIN) & (material == mat.ARM)
    )
    base[use_second] = second[use_second]
    front = unit_point[:, 0] > 0
    base[(region == mat.LIGHT) & front] = HEADLIGHT
    base[(region == mat.LIGHT) & ~front] = TAILLIGHT
    base[region == mat.PLATE] = PLATE_COLOUR
    base[region == mat.GLASS] = GLASS_COLOUR

    x, y, z = world_point[:, 0], world_point[:, 1], world_point[:, 2]
    grain = noise.fractal(x + 0.7 * y, z + 0.3 * y, 0.6, footprint, 3, tile=1)
    window = region == mat.WINDOW
    cell = noise.sample(np.floor((x + y) / 3.1) * 7.3, np.floor(z / 3.2) * 3.1, tile=2)
    base[window] = WINDOW_COLOUR * (0.6 + 0.9 * cell[window, None])
    rough = np.isin(material, (mat.WALL, mat.CONCRETE, mat.PLASTIC, mat.BARK))
    base[rough] *= (1.0 + 0.35 * grain[rough])[:, None]
    facade = (material == mat.FACADE) & ~window
    base[facade] *= (1.0 + 0.12 * grain[facade])[:, None]
    bark = material == mat.BARK
    streak = noise.fractal(
        np.arctan2(unit_point[:, 1], unit_point[:, 0]) * 6.0, z * 0.4, 0.5, 0.0, 2, tile=3
    )
    base[bark] *= (1.0 + 0.6 * streak[bark])[:, None]
    foliage = material == mat.FOLIAGE
    if np.any(foliage):
        fx, fy, fz, fp = x[foliage], y[foliage], z[foliage], footprint[foliage]
        leaves = noise.fractal(fx, fz, 0.6, fp, 3, tile=0) + noise.fractal(
            fy, fz + 17.0, 0.6, fp, 3, tile=2
        )
        base[foliage] *= np.clip(1.0 + 1.6 * leaves, 0.25, 2.0)[:, None]
    cloth = np.isin(material, (mat.CLOTH, mat.ARM))
    base[cloth] *= (1.0 + 0.15 * grain[cloth])[:, None]

    sun_cos = np.clip(np.einsum("ki,i->k", normal, light.sun), 0.0, None)
    sky = light.ambient * (0.8 + 0.2 * normal[:, 2])
    if np.any(foliage):
        sky[foliage] *= 0.75 + 0.25 * np.clip(unit_point[foliage, 2] + 0.5, 0, 1)
    colour = base * (sky + light.sun_strength * sun_cos)[:, None]

    glossy = np.isin(region, (mat.PAINT, mat.GLASS)) & np.isin(
        material, (mat.CAR_BODY, mat.CAR_CABIN)
    )
    reflect = view - 2.0 * np.einsum("ki,ki->k", view, normal)[:, None] * normal
    highlight = np.clip(np.einsum("ki,i->k", reflect, light.sun), 0, 1) ** 40 * light.sun_strength
    fresnel = 0.04 + 0.5 * (1.0 - np.clip(-np.einsum("ki,ki->k", view, normal), 0, 1)) ** 5
    sky_seen = light.sky_horizon * np.clip(reflect[:, 2] * 3 + 0.4, 0.3, 1.0)[:, None]
    strength = np.where(region == mat.GLASS, 0.35, 0.12)
    gloss = strength * (fresnel + 0.3) * 0.6
    colour[glossy] += gloss[glossy, None] * sky_seen[glossy] + 0.8 * highlight[glossy, None]
    return colour


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """(N, 2) points -> (M, 2) hull vertices, counter-clockwise (Andrew's monotone chain)."""
    order = np.lexsort((points[:, 1], points[:, 0]))
    pts = points[order]

    def half(sequence: np.ndarray) -> list[np.ndarray]:
        chain: list[np.ndarray] = []
        for p in sequence:
            while len(chain) >= 2:
                a, b = chain[-2], chain[-1]
                if (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) > 0:
                    break
                chain.pop()
            chain.append(p)
        return chain

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def ground_shadow(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N,) LiDAR-frame ground points -> (N,) fraction of sunlight they keep (0 in shadow, a
    darker 0 under vehicles, 1 in the sun)."""
    sun = scene.lighting.sun
    lit = np.ones(len(x))
    if len(x) == 0 or not scene.objects:
        return lit
    order = np.argsort(x, kind="stable")
    x_sorted = x[order]
    boxes = scene.boxes("all").copy()
    for index, obj in enumerate(scene.objects):  # people are slimmer than their boxes
        boxes[index, 3:5] *= _SHADOW_SLIMMING.get(obj.kind, (1.0, 1.0))
    corners = bev_corners(boxes)
    top = boxes[:, 5]  # objects stand on the ground: their top is their height
    shift = -sun[:2] / sun[2]
    for index, obj in enumerate(scene.objects):
        if obj.round_shadow:
            centre = boxes[index, :2] + shift * (top[index] - boxes[index, 5] * 0.3)
            polygon = centre + 0.5 * min(boxes[index, 3], boxes[index, 4]) * _UNIT_CIRCLE
        else:
            polygon = _convex_hull(
                np.concatenate([corners[index], corners[index] + shift * top[index]])
            )
        lo, hi = np.searchsorted(x_sorted, [polygon[:, 0].min(), polygon[:, 0].max()])
        if hi <= lo:
            continue
        candidates = order[lo:hi]
        py = y[candidates]
        candidates = candidates[(py >= polygon[:, 1].min()) & (py <= polygon[:, 1].max())]
        if candidates.size == 0:
            continue
        px, py = x[candidates], y[candidates]
        start, end = polygon, np.roll(polygon, -1, axis=0)
        side = (end[None, :, 0] - start[None, :, 0]) * (py[:, None] - start[None, :, 1]) - (
            end[None, :, 1] - start[None, :, 1]
        ) * (px[:, None] - start[None, :, 0])
        inside = np.all(side >= 0, axis=1)
        lit[candidates[inside]] = 0.0
    return lit


def contact_darkening(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N,) ground points -> (N,) ambient-light factor: darker right under road users."""
    factor = np.ones(len(x))
    boxes = scene.boxes("labelled")
    if len(boxes) == 0 or len(x) == 0:
        return factor
    for box in boxes:
        dx, dy = x - box[0], y - box[1]
        near = np.abs(dx) + np.abs(dy) < box[3] + box[4]
        if not near.any():
            continue
        c, s = np.cos(box[6]), np.sin(box[6])
        lx = dx[near] * c + dy[near] * s
        ly = -dx[near] * s + dy[near] * c
        depth = np.maximum(np.abs(lx) - box[3] / 2, np.abs(ly) - box[4] / 2)
        factor[near] = np.minimum(factor[near], np.clip(0.45 + depth / 0.25, 0.45, 1.0))
    return factor
