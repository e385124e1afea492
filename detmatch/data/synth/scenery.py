"""Unlabelled things: pedestrian-sized clutter and the roadside background.

Clutter is the camera-easy, LiDAR-hard failure mode: posts, bollards, cabinets, bins, sign
posts and tree trunks of a person's width (0.3-0.8 m) and height (1.2-2.2 m), reflecting like
clothing, but grey, brown or green and without head, skin or clothing in the image. World v2
adds things whose point signature is a person's or a cyclist's: pay stations (a narrow
pedestal, a wider body, a rounded top: legs, torso and head to a 64-beam sensor), shrubs of a
person's size, and parked bicycles without riders, one to three side by side.
"""

from __future__ import annotations

import numpy as np

from detmatch.data.synth import materials as mat
from detmatch.data.synth.primitives import Primitives
from detmatch.data.synth.shapes import ShapeBuilder, build_bicycle
from detmatch.data.synth.world import WORLDS

CLUTTER_KINDS = tuple(dict.fromkeys(k for w in WORLDS.values() for k in w.clutter_kinds))
GREYS = np.array([[0.55, 0.55, 0.53], [0.42, 0.43, 0.42], [0.66, 0.65, 0.62], [0.30, 0.31, 0.31]])
DULL_COLOURS = np.array(
    [
        [0.18, 0.30, 0.22],
        [0.45, 0.45, 0.43],
        [0.60, 0.58, 0.52],
        [0.25, 0.25, 0.27],
        [0.38, 0.30, 0.22],
        [0.52, 0.52, 0.50],
    ]
)
BARK_COLOURS = np.array([[0.33, 0.25, 0.18], [0.40, 0.32, 0.24], [0.26, 0.21, 0.16]])
SIGN_FACES = np.array(
    [[0.92, 0.92, 0.90], [0.15, 0.30, 0.70], [0.75, 0.12, 0.10], [0.9, 0.75, 0.1]]
)
FACADE_COLOURS = np.array(
    [
        [0.82, 0.77, 0.66],
        [0.88, 0.87, 0.83],
        [0.64, 0.36, 0.27],
        [0.70, 0.68, 0.64],
        [0.78, 0.70, 0.50],
        [0.55, 0.58, 0.62],
        [0.74, 0.60, 0.48],
        [0.93, 0.90, 0.80],
    ]
)
FOLIAGE_COLOURS = np.array(
    [[0.20, 0.32, 0.12], [0.26, 0.38, 0.14], [0.16, 0.26, 0.10], [0.30, 0.36, 0.16]]
)


def _pick(rng: np.random.Generator, palette: np.ndarray, jitter: float = 0.08) -> np.ndarray:
    return np.clip(palette[rng.integers(len(palette))] * rng.uniform(1 - jitter, 1 + jitter), 0, 1)


def build_clutter(rng: np.random.Generator, kind: str, owner: int) -> Primitives:
    """One pedestrian-sized clutter object of the given kind (see CLUTTER_KINDS)."""
    builder = ShapeBuilder()
    height = rng.uniform(1.2, 2.2)
    if kind == "post":
        half = rng.uniform(0.15, 0.25)
        colour = _pick(rng, np.concatenate([GREYS, DULL_COLOURS]))
        material = mat.CONCRETE if rng.random() < 0.5 else mat.METAL
        builder.box((-half, -half, 0.0), (half, half, height), material, colour)
    elif kind == "bollard":
        height = rng.uniform(1.1, 1.6)
        builder.post((0.0, 0.0), rng.uniform(0.15, 0.32), height, mat.CONCRETE, _pick(rng, GREYS))
    elif kind == "cabinet":
        height = rng.uniform(1.2, 1.7)
        lx, ly = rng.uniform(0.2, 0.4), rng.uniform(0.15, 0.25)
        builder.box((-lx, -ly, 0.0), (lx, ly, height), mat.PLASTIC, _pick(rng, DULL_COLOURS))
    elif kind == "bin":
        height = rng.uniform(1.1, 1.35)
        builder.post(
            (0.0, 0.0), rng.uniform(0.22, 0.34), height, mat.PLASTIC, _pick(rng, DULL_COLOURS)
        )
    elif kind == "sign":
        pole = _pick(rng, GREYS)
        builder.post((0.0, 0.0), 0.045, height - 0.3, mat.METAL, pole)
        plate = rng.uniform(0.25, 0.35)
        builder.box(
            (-0.03, -plate, height - 2 * plate),
            (0.03, plate, height),
            mat.SIGN,
            pole,
            _pick(rng, SIGN_FACES, 0.0),
        )
    elif kind == "trunk":
        builder.post((0.0, 0.0), rng.uniform(0.15, 0.3), height, mat.BARK, _pick(rng, BARK_COLOURS))
    elif kind == "pay_station":
        _pay_station(builder, rng)
    elif kind == "shrub":
        leaves = _pick(rng, FOLIAGE_COLOURS, 0.15)
        radii = np.array([rng.uniform(0.28, 0.42), rng.uniform(0.25, 0.4), 0.0])
        radii[2] = rng.uniform(0.6, 0.95)
        builder.ellipsoid((0.0, 0.0, radii[2]), radii, mat.FOLIAGE, leaves)
        top = radii * rng.uniform(0.45, 0.6)
        builder.ellipsoid((0.0, 0.0, 2 * radii[2] - top[2] * 0.6), top, mat.FOLIAGE, leaves * 0.9)
    elif kind == "bicycles":
        length, width = rng.uniform(1.6, 1.85), rng.uniform(0.5, 0.65)
        count = int(rng.integers(1, 4))
        spacing = rng.uniform(0.55, 0.8)
        for i in range(count):
            build_bicycle(builder, rng, length, width, (i - (count - 1) / 2) * spacing)
    else:
        raise ValueError(f"unknown clutter kind {kind!r}; expected one of {CLUTTER_KINDS}")
    return builder.build(owner)


def _pay_station(builder: ShapeBuilder, rng: np.random.Generator) -> None:
    """A ticket machine: pedestal, body and a rounded top, 1.5-1.85 m tall."""
    body_colour = _pick(rng, np.concatenate([GREYS, DULL_COLOURS]))
    pedestal = rng.uniform(0.75, 0.95)
    body_top = pedestal + rng.uniform(0.5, 0.65)
    half_width, half_depth = rng.uniform(0.2, 0.3), rng.uniform(0.12, 0.18)
    builder.post((0.0, 0.0), rng.uniform(0.1, 0.16), pedestal, mat.METAL, _pick(rng, GREYS))
    builder.box(
        (-half_depth, -half_width, pedestal), (half_depth, half_width, body_top),
        mat.PLASTIC, body_colour,
    )  # fmt: skip
    cap = np.array([rng.uniform(0.09, 0.13), rng.uniform(0.09, 0.13), rng.uniform(0.1, 0.14)])
    builder.ellipsoid((0.0, 0.0, body_top + cap[2]), cap, mat.PLASTIC, body_colour * 0.8)


def build_building(
    rng: np.random.Generator, length: float, depth: float, height: float, owner: int
) -> Primitives:
    """A block: facade with a window grid (along x and y faces), darker flat roof."""
    builder = ShapeBuilder()
    colour = _pick(rng, FACADE_COLOURS)
    roof = np.clip(colour * 0.55, 0, 1)
    builder.box(
        (-length / 2, -depth / 2, 0.0), (length / 2, depth / 2, height), mat.FACADE, colour, roof
    )
    return builder.build(owner)


def build_tree(rng: np.random.Generator, owner: int) -> Primitives:
    """A roadside tree: bark trunk into a foliage crown."""
    builder = ShapeBuilder()
    crown = np.array([rng.uniform(1.4, 3.2), 0.0, rng.uniform(1.5, 3.0)])
    crown[1] = crown[0] * rng.uniform(0.85, 1.15)
    trunk_height = rng.uniform(2.2, 4.0)
    builder.post(
        (0.0, 0.0),
        rng.uniform(0.12, 0.28),
        trunk_height + crown[2] * 0.5,
        mat.BARK,
        _pick(rng, BARK_COLOURS),
    )
    leaves = _pick(rng, FOLIAGE_COLOURS, 0.15)
    builder.ellipsoid((0.0, 0.0, trunk_height + crown[2]), crown, mat.FOLIAGE, leaves)
    for _ in range(int(rng.integers(2, 4))):  # lumps that break the crown's outline
        radii = crown * rng.uniform(0.45, 0.65)
        direction = rng.normal(size=3) * np.array([1.0, 1.0, 0.6])
        offset = crown * 0.7 * direction / np.linalg.norm(direction)
        centre = np.array([0.0, 0.0, trunk_height + crown[2]]) + offset
        builder.ellipsoid(
            centre, radii, mat.FOLIAGE, np.clip(leaves * rng.uniform(0.85, 1.15), 0, 1)
        )
    return builder.build(owner)


def build_hedge(rng: np.random.Generator, length: float, owner: int) -> Primitives:
    builder = ShapeBuilder()
    depth, height = rng.uniform(0.7, 1.5), rng.uniform(0.9, 2.2)
    builder.box(
        (-length / 2, -depth / 2, 0.0),
        (length / 2, depth / 2, height),
        mat.FOLIAGE,
        _pick(rng, FOLIAGE_COLOURS, 0.15),
    )
    return builder.build(owner)


def build_wall(rng: np.random.Generator, length: float, owner: int) -> Primitives:
    """A garden or boundary wall, brick or concrete, with a coping on top."""
    builder = ShapeBuilder()
    height = rng.uniform(0.8, 2.4)
    colour = _pick(rng, np.concatenate([GREYS, FACADE_COLOURS[[2, 6]]]))
    builder.box(
        (-length / 2, -0.15, 0.0), (length / 2, 0.15, height), mat.WALL, colour, colour * 0.7
    )
    return builder.build(owner)


def build_guardrail(rng: np.random.Generator, length: float, owner: int) -> Primitives:
    """A steel crash barrier on posts every 4 m."""
    builder = ShapeBuilder()
    steel = _pick(rng, GREYS[[0, 2]], 0.05)
    builder.box((-length / 2, -0.05, 0.45), (length / 2, 0.05, 0.8), mat.GUARDRAIL, steel)
    for x in np.arange(-length / 2 + 0.5, length / 2, 4.0):
        builder.box((x - 0.06, 0.04, 0.0), (x + 0.06, 0.14, 0.75), mat.METAL, steel * 0.7)
    return builder.build(owner)
