"""Procedural textures: value noise, the road surface and the sky.

Textures are functions of world position (metres), so the same surface looks the same from
every pixel; fine detail fades where a pixel covers more ground than the detail's size.
"""

from __future__ import annotations

import numpy as np

from detmatch.data.synth.scene import Lighting, RoadLayout

TILE = 128
ASPHALT = np.array([0.36, 0.36, 0.37])
MARKING = np.array([0.88, 0.88, 0.86])
CURB_COLOUR = np.array([0.62, 0.61, 0.58])
PAVING = np.array([0.58, 0.56, 0.52])
GRASS = np.array([0.30, 0.38, 0.16])
DIRT = np.array([0.45, 0.40, 0.30])


class NoiseTiles:
    """Tileable value noise: 4 random TILE x TILE grids, sampled bilinearly with wrap-around."""

    def __init__(self, seed: int) -> None:
        self.tiles = np.random.default_rng(seed).random((4, TILE, TILE))

    def sample(self, x: np.ndarray, y: np.ndarray, tile: int = 0) -> np.ndarray:
        """(N,) grid coordinates -> (N,) smooth noise in [0, 1]."""
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
        i0 = x0.astype(np.int64) % TILE
        j0 = y0.astype(np.int64) % TILE
        i1, j1 = (i0 + 1) % TILE, (j0 + 1) % TILE
        grid = self.tiles[tile]
        top = grid[j0, i0] * (1 - fx) + grid[j0, i1] * fx
        bottom = grid[j1, i0] * (1 - fx) + grid[j1, i1] * fx
        return top * (1 - fy) + bottom * fy

    def fractal(
        self,
        x: np.ndarray,
        y: np.ndarray,
        scale: float,
        footprint: np.ndarray | float,
        octaves: int = 3,
        tile: int = 0,
    ) -> np.ndarray:
        """(N,) positions in metres -> (N,) zero-mean noise about [-0.5, 0.5]; an octave of
        feature size `scale` fades out where a pixel's footprint (metres) exceeds it."""
        total = np.zeros(np.shape(x))
        amplitude = 1.0
        for octave in range(octaves):
            fade = np.clip(1.5 - np.asarray(footprint) / scale, 0.0, 1.0)
            total += (
                amplitude * fade * (self.sample(x / scale, y / scale, (tile + octave) % 4) - 0.5)
            )
            scale, amplitude = scale / 2.3, amplitude * 0.6
        return total


def _band(distance: np.ndarray, half_width: float, footprint: np.ndarray) -> np.ndarray:
    """Coverage in [0, 1] of the band |distance| < half_width by a pixel of width footprint
    centred at distance (a box filter: thin far lines fade to their average coverage)."""
    footprint = np.maximum(footprint, 1e-3)
    overlap = np.minimum(half_width, distance + footprint / 2) - np.maximum(
        -half_width, distance - footprint / 2
    )
    return np.clip(overlap / footprint, 0.0, 1.0)


def road_surface(
    road: RoadLayout,
    x: np.ndarray,
    y: np.ndarray,
    footprint: np.ndarray,
    along_footprint: np.ndarray,
    noise: NoiseTiles,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground colour and LiDAR reflectivity at LiDAR-frame ground points.

    x, y: (N,) metres; footprint, along_footprint: (N,) ground one pixel covers across and
    along the line of sight, metres.
    Returns ((N, 3) RGB in [0, 1], (N,) reflectivity).
    """
    s, u = road.to_road(x, y)
    colour = np.empty((len(x), 3))
    reflectivity = np.empty(len(x))

    on_road = (u >= road.road_right) & (u <= road.road_left)
    grain = noise.fractal(s, u, 4.0, footprint, 3, tile=0)
    speckle = noise.fractal(s * 3.1, u * 3.1, 0.15, footprint, 2, tile=2)
    asphalt = ASPHALT * (1.0 + 0.22 * grain + 0.25 * speckle)[:, None]
    marking = np.zeros(len(x))
    dash = np.where(along_footprint > 3.0, 1 / 3, (np.mod(s, 9.0) < 3.0).astype(np.float64))
    lanes = np.arange(
        round(road.lanes_right / road.lane_width), round(road.lanes_left / road.lane_width) + 1
    )
    for k in lanes:
        line_u = k * road.lane_width
        edge = k in (lanes[0], lanes[-1])
        cover = _band(u - line_u, 0.08 if edge else 0.06, footprint)
        marking = np.maximum(marking, cover if edge or k == 0 and len(lanes) > 3 else cover * dash)
    road_colour = asphalt * (1 - marking[:, None]) + MARKING * marking[:, None] * (
        0.9 + 0.1 * grain[:, None]
    )
    colour[on_road] = road_colour[on_road]
    reflectivity[on_road] = (0.27 + 0.06 * grain + 0.4 * marking)[on_road]

    beyond = np.where(u > road.road_left, u - road.road_left, road.road_right - u)
    walk = np.where(u > road.road_left, road.sidewalk_left, road.sidewalk_right)
    curb = ~on_road & (beyond < 0.25)
    colour[curb] = CURB_COLOUR * (1.0 + 0.1 * grain[curb, None])
    reflectivity[curb] = 0.34
    tiles_seam = np.minimum(np.abs(np.mod(s, 0.6) - 0.3), np.abs(np.mod(u, 0.6) - 0.3))
    seam = (tiles_seam > 0.28).astype(np.float64) * np.clip(1.5 - footprint / 0.05, 0, 1)
    paving = PAVING * (1.0 + 0.12 * grain - 0.15 * seam)[:, None]
    sidewalk = ~on_road & ~curb & (beyond < 0.25 + walk)
    colour[sidewalk] = paving[sidewalk]
    reflectivity[sidewalk] = 0.3
    verge = ~on_road & ~curb & ~sidewalk
    patch = noise.fractal(s, u, 6.0, footprint, 2, tile=1)
    mix = np.clip(0.5 + 1.6 * patch, 0, 1)[:, None]
    grass = (GRASS * mix + DIRT * (1 - mix)) * (1.0 + 0.6 * speckle + 0.3 * grain)[:, None]
    colour[verge] = grass[verge]
    reflectivity[verge] = 0.24
    return np.clip(colour, 0, 1), reflectivity


def sky_colour(lighting: Lighting, dirs: np.ndarray, noise: NoiseTiles) -> np.ndarray:
    """(N, 3) unit view directions -> (N, 3) sky RGB: horizon-to-zenith gradient, soft clouds,
    brighter towards the sun."""
    elevation = np.arcsin(np.clip(dirs[:, 2], -1, 1))
    t = np.clip(elevation / 0.45, 0, 1)[:, None] ** 0.7
    colour = lighting.sky_horizon * (1 - t) + lighting.sky_top * t
    azimuth = np.arctan2(dirs[:, 1], dirs[:, 0])
    cloud = noise.fractal(azimuth * 14.0, elevation * 40.0, 3.0, 0.0, 3, tile=3)
    cloud = np.clip(cloud * 2.2, 0, 1)[:, None]
    colour = colour * (1 - 0.7 * cloud) + 0.95 * cloud
    glow = np.clip(np.einsum("ki,i->k", dirs, lighting.sun), 0, 1)[:, None] ** 8
    return np.clip(colour + 0.25 * glow, 0, 1)
