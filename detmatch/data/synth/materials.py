"""Materials of the synthetic world and the regions a surface point falls in.

A primitive has one material; a material may split its surface into regions (a car cabin into
glass and roof, a head into face and hair, a facade into wall and windows). Both sensors look
regions up: the camera for colour, the LiDAR for reflectivity and dropout.
"""

from __future__ import annotations

import numpy as np

CAR_BODY, CAR_CABIN, TYRE, HEAD, CLOTH, ARM, BIKE, METAL = 0, 1, 2, 3, 4, 5, 6, 7
BARK, CONCRETE, FACADE, FOLIAGE, WALL, PLASTIC, GUARDRAIL, SIGN = 8, 9, 10, 11, 12, 13, 14, 15
NUM_MATERIALS = 16

# Regions: what a point of a surface is made of.
PAINT, GLASS, LIGHT, PLATE, SKIN, HAIR, WINDOW, ROOF, BASE, SECOND = range(10)
NUM_REGIONS = 10

# LiDAR reflectivity (KITTI intensity scale, 0..1) and extra dropout by material, for the
# BASE region; regions below override. Clutter (METAL, BARK, CONCRETE, PLASTIC) reflects like
# clothing on purpose: in the point cloud it is as ambiguous as a pedestrian.
MATERIAL_REFLECTIVITY = np.array(
    [0.32, 0.32, 0.05, 0.24, 0.27, 0.27, 0.30, 0.29, 0.24, 0.30, 0.30, 0.16, 0.28, 0.27, 0.62, 0.9]
)
MATERIAL_DROPOUT = np.array(
    [0.0, 0.0, 0.05, 0.02, 0.02, 0.02, 0.05, 0.02, 0.02, 0.0, 0.0, 0.15, 0.0, 0.02, 0.0, 0.0]
)
REGION_REFLECTIVITY = {GLASS: 0.07, LIGHT: 0.7, PLATE: 0.85, WINDOW: 0.1, HAIR: 0.15}
REGION_DROPOUT = {GLASS: 0.45, WINDOW: 0.35}


def surface_regions(
    material: np.ndarray, unit_point: np.ndarray, half_size: np.ndarray
) -> np.ndarray:
    """(K,) materials, (K, 3) unit-space hit points, (K, 3) primitive half sizes (metres) -> (K,)
    region ids.

    Box faces are told apart by the unit coordinate of largest magnitude: +x front, -x rear,
    +-y sides, +z top.
    """
    region = np.full(material.shape, BASE, dtype=np.int64)
    x, y, z = unit_point[:, 0], unit_point[:, 1], unit_point[:, 2]
    face = np.argmax(np.abs(unit_point), axis=1)
    on_side = face == 1
    on_end = face == 0
    on_top = (face == 2) & (z > 0)

    body = material == CAR_BODY
    region[body] = PAINT
    length, width, height = (2 * half_size[:, i] for i in range(3))
    lateral_m = np.abs(y) * width / 2
    light = body & on_end & (lateral_m > width / 2 - 0.38) & (z > 0.1) & (z < 0.75)
    plate = body & on_end & (lateral_m < 0.26) & (z > -0.55) & (z < -0.05)
    region[light] = LIGHT
    region[plate] = PLATE

    cabin = material == CAR_CABIN
    region[cabin] = PAINT
    pillar_m = 0.09
    side_glass = (
        on_side & (np.abs(x) * length / 2 < length / 2 - pillar_m) & (z > -0.75) & (z < 0.8)
    )
    end_glass = on_end & (lateral_m < width / 2 - pillar_m) & (z > -0.7) & (z < 0.85)
    region[cabin & (side_glass | end_glass)] = GLASS

    head = material == HEAD
    region[head] = SKIN
    region[head & ((z > 0.25) | ((x < -0.2) & (z > -0.5)))] = HAIR

    arm = material == ARM
    region[arm] = BASE
    region[arm & (z > 0.55)] = SKIN

    facade = material == FACADE
    region[facade] = PAINT
    region[facade & on_top] = ROOF
    along = np.where(on_side, x * length / 2, y * width / 2)
    up_m = (z + 1) * height / 2
    window = (
        facade
        & (on_side | on_end)
        & (np.mod(along, 3.1) > 0.9)
        & (np.mod(up_m, 3.2) > 1.0)
        & (np.mod(up_m, 3.2) < 2.6)
        & (up_m > 3.0)
        & (up_m < height - 0.8)
    )
    region[window] = WINDOW

    second = ((material == SIGN) & on_end) | ((material == WALL) & on_top)
    region[second] = SECOND
    return region


def reflectivity_and_dropout(
    material: np.ndarray, region: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(K,) materials and regions -> ((K,) mean LiDAR intensity, (K,) extra dropout chance)."""
    reflectivity = MATERIAL_REFLECTIVITY[material].copy()
    dropout = MATERIAL_DROPOUT[material].copy()
    for region_id, value in REGION_REFLECTIVITY.items():
        reflectivity[region == region_id] = value
    for region_id, value in REGION_DROPOUT.items():
        dropout[region == region_id] = value
    return reflectivity, dropout
