"""Objects built from primitives, in an object frame: x along the heading, y left, z up, the
origin on the ground below the object's centre.

Each builder fills the extent it is asked for, so an object's tight box (the label) is the
box the caller sampled up to small differences, and every primitive lies inside it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detmatch.data.synth import materials as mat
from detmatch.data.synth.primitives import BOX, CYLINDER, ELLIPSOID, Primitives

_IDENTITY = np.eye(3)
# A wheel: cylinder axis (local z) along the object's y.
_WHEEL_ROTATION = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

CAR_COLOURS = np.array(
    [
        [0.85, 0.86, 0.87],
        [0.62, 0.64, 0.66],
        [0.12, 0.12, 0.13],
        [0.35, 0.36, 0.38],
        [0.55, 0.08, 0.07],
        [0.10, 0.17, 0.36],
        [0.72, 0.72, 0.70],
        [0.25, 0.30, 0.28],
        [0.45, 0.40, 0.33],
        [0.80, 0.78, 0.72],
        [0.18, 0.22, 0.30],
    ]
)
SKIN_COLOURS = np.array(
    [
        [0.87, 0.70, 0.58],
        [0.76, 0.57, 0.44],
        [0.55, 0.38, 0.27],
        [0.35, 0.24, 0.17],
        [0.93, 0.78, 0.68],
    ]
)
HAIR_COLOURS = np.array(
    [
        [0.08, 0.06, 0.05],
        [0.30, 0.20, 0.12],
        [0.72, 0.60, 0.38],
        [0.55, 0.55, 0.55],
        [0.18, 0.12, 0.08],
    ]
)
SHIRT_COLOURS = np.array(
    [
        [0.90, 0.90, 0.88],
        [0.10, 0.10, 0.12],
        [0.70, 0.12, 0.12],
        [0.15, 0.30, 0.65],
        [0.20, 0.45, 0.25],
        [0.85, 0.70, 0.15],
        [0.50, 0.50, 0.52],
        [0.55, 0.25, 0.50],
        [0.95, 0.45, 0.15],
        [0.35, 0.55, 0.75],
    ]
)
TROUSER_COLOURS = np.array(
    [
        [0.16, 0.22, 0.38],
        [0.08, 0.08, 0.09],
        [0.35, 0.35, 0.37],
        [0.62, 0.55, 0.42],
        [0.30, 0.22, 0.15],
        [0.22, 0.30, 0.48],
    ]
)


class ShapeBuilder:
    """Collects the primitives of one object in its object frame."""

    def __init__(self) -> None:
        self._kind: list[int] = []
        self._center: list[np.ndarray] = []
        self._rotation: list[np.ndarray] = []
        self._half: list[np.ndarray] = []
        self._material: list[int] = []
        self._colour: list[np.ndarray] = []
        self._colour2: list[np.ndarray] = []

    def add(
        self,
        kind: int,
        center: np.ndarray,
        rotation: np.ndarray,
        half_size: np.ndarray,
        material: int,
        colour: np.ndarray,
        colour2: np.ndarray | None = None,
    ) -> None:
        """One primitive; center (3,), rotation (3, 3) columns = its axes, half_size (3,)."""
        self._kind.append(kind)
        self._center.append(np.asarray(center, dtype=np.float64))
        self._rotation.append(np.asarray(rotation, dtype=np.float64))
        self._half.append(np.maximum(np.asarray(half_size, dtype=np.float64), 1e-3))
        self._material.append(material)
        self._colour.append(np.asarray(colour, dtype=np.float64))
        self._colour2.append(np.asarray(colour if colour2 is None else colour2, dtype=np.float64))

    def box(self, low: tuple, high: tuple, material: int, colour, colour2=None) -> None:
        """Axis-aligned box from corner low (3,) to corner high (3,)."""
        low, high = np.asarray(low, float), np.asarray(high, float)
        self.add(BOX, (low + high) / 2, _IDENTITY, (high - low) / 2, material, colour, colour2)

    def segment(
        self, start, end, half_width: float, half_depth: float, material: int, colour, colour2=None
    ) -> None:
        """Box from point start to end (its local z), half_width along y-ish, half_depth x-ish."""
        start, end = np.asarray(start, float), np.asarray(end, float)
        axis = end - start
        length = np.linalg.norm(axis)
        z = axis / length
        helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        rotation = np.stack([x, y, z], axis=1)
        half = (half_depth, half_width, length / 2)
        self.add(BOX, (start + end) / 2, rotation, half, material, colour, colour2)

    def wheel(self, center, radius: float, half_width: float, material: int, colour) -> None:
        """Cylinder with its axis along the object's y."""
        self.add(CYLINDER, center, _WHEEL_ROTATION, (radius, radius, half_width), material, colour)

    def post(self, center_xy, radius: float, height: float, material: int, colour, z0=0.0) -> None:
        """Vertical cylinder standing on z0."""
        center = (center_xy[0], center_xy[1], z0 + height / 2)
        self.add(CYLINDER, center, _IDENTITY, (radius, radius, height / 2), material, colour)

    def ellipsoid(self, center, radii, material: int, colour, colour2=None) -> None:
        self.add(ELLIPSOID, center, _IDENTITY, radii, material, colour, colour2)

    def build(self, owner: int) -> Primitives:
        """The collected primitives (object frame), all owned by `owner`."""
        n = len(self._kind)
        return Primitives(
            kind=np.array(self._kind, dtype=np.int64),
            center=np.array(self._center).reshape(n, 3),
            rotation=np.array(self._rotation).reshape(n, 3, 3),
            half_size=np.array(self._half).reshape(n, 3),
            material=np.array(self._material, dtype=np.int64),
            colour=np.array(self._colour).reshape(n, 3),
            colour2=np.array(self._colour2).reshape(n, 3),
            owner=np.full(n, owner, dtype=np.int64),
        )


def local_extent(prims: Primitives) -> tuple[np.ndarray, np.ndarray]:
    """(min (3,), max (3,)) of the primitives' bounding boxes in their frame (exact for boxes
    and axis-aligned cylinders, tight for ellipsoids)."""
    rotation_abs = np.abs(prims.rotation)
    box_extent = np.einsum("pij,pj->pi", rotation_abs, prims.half_size)
    ellipsoid_extent = np.sqrt(np.einsum("pij,pj->pi", prims.rotation**2, prims.half_size**2))
    extent = np.where((prims.kind == ELLIPSOID)[:, None], ellipsoid_extent, box_extent)
    return (prims.center - extent).min(axis=0), (prims.center + extent).max(axis=0)


def place(
    prims: Primitives, x: float, y: float, yaw: float, ground_z: float
) -> tuple[Primitives, np.ndarray]:
    """Object-frame primitives -> (world primitives, (7,) tight LiDAR-frame box).

    The object is lifted so its lowest point touches the ground; (x, y) is where the object
    frame's origin goes, yaw its heading.
    """
    low, high = local_extent(prims)
    lift = -low[2]
    c, s = np.cos(yaw), np.sin(yaw)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    offset = np.array([x, y, ground_z + lift])
    world = Primitives(
        kind=prims.kind,
        center=np.einsum("pj,ij->pi", prims.center, rz) + offset,
        rotation=np.einsum("ij,pjk->pik", rz, prims.rotation),
        half_size=prims.half_size,
        material=prims.material,
        colour=prims.colour,
        colour2=prims.colour2,
        owner=prims.owner,
    )
    box_center = rz @ ((low + high) / 2) + offset
    dims = high - low
    return world, np.array([*box_center, dims[0], dims[1], dims[2], yaw])


def build_car(
    rng: np.random.Generator, length: float, width: float, height: float, owner: int
) -> Primitives:
    """A car filling length x width x height: body, cabin with glass, bumpers, four wheels."""
    builder = ShapeBuilder()
    colour = CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.9, 1.08)
    colour = np.clip(colour, 0, 1)
    trim = np.array([0.07, 0.07, 0.08])
    l2, w2 = length / 2, width / 2
    belt = height * rng.uniform(0.55, 0.62)
    sill = 0.28
    builder.box((-l2 + 0.02, -w2, sill), (l2 - 0.02, w2, belt), mat.CAR_BODY, colour)
    for sign in (-1.0, 1.0):
        front = sign * l2
        inner = sign * (l2 - 0.3)
        builder.box(
            (min(front, inner), -w2 + 0.03, 0.06),
            (max(front, inner), w2 - 0.03, sill + 0.02),
            mat.PLASTIC,
            trim,
        )
    cabin_length = length * rng.uniform(0.46, 0.58)
    cabin_center = -length * rng.uniform(0.02, 0.1)
    inset = rng.uniform(0.07, 0.14)
    builder.box(
        (cabin_center - cabin_length / 2, -w2 + inset, belt - 0.01),
        (cabin_center + cabin_length / 2, w2 - inset, height),
        mat.CAR_CABIN,
        colour,
    )
    radius = rng.uniform(0.29, 0.34)
    axle = l2 - rng.uniform(0.72, 0.92)
    for wx in (-axle, axle):
        for wy in (-(w2 - 0.12), w2 - 0.12):
            builder.wheel((wx, wy, radius), radius, 0.11, mat.TYRE, trim)
    return builder.build(owner)


def build_van(
    rng: np.random.Generator, length: float, width: float, height: float, owner: int
) -> Primitives:
    """A van: tall box body with a short bonnet, windscreen and side windows, wheels."""
    builder = ShapeBuilder()
    colour = np.clip(CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.95, 1.1), 0, 1)
    trim = np.array([0.07, 0.07, 0.08])
    l2, w2 = length / 2, width / 2
    bonnet = rng.uniform(0.7, 1.0)
    builder.box((-l2, -w2, 0.3), (l2 - bonnet, w2, height * 0.55), mat.CAR_BODY, colour)
    builder.box((l2 - bonnet, -w2, 0.3), (l2, w2, height * 0.5), mat.CAR_BODY, colour)
    builder.box(
        (l2 - bonnet - 1.4, -w2 + 0.03, height * 0.55),
        (l2 - bonnet, w2 - 0.03, height),
        mat.CAR_CABIN,
        colour,
    )
    builder.box((-l2, -w2, height * 0.55), (l2 - bonnet - 1.4, w2, height), mat.CAR_CABIN, colour)
    for sign in (-1.0, 1.0):
        a, b = sign * l2, sign * (l2 - 0.25)
        builder.box((min(a, b), -w2 + 0.03, 0.07), (max(a, b), w2 - 0.03, 0.32), mat.PLASTIC, trim)
    radius = rng.uniform(0.32, 0.37)
    for wx in (-(l2 - 0.85), l2 - bonnet - 0.2):
        for wy in (-(w2 - 0.13), w2 - 0.13):
            builder.wheel((wx, wy, radius), radius, 0.12, mat.TYRE, trim)
    return builder.build(owner)


def _person_colours(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    skin = SKIN_COLOURS[rng.integers(len(SKIN_COLOURS))]
    hair = HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))]
    shirt = np.clip(SHIRT_COLOURS[rng.integers(len(SHIRT_COLOURS))] * rng.uniform(0.85, 1.1), 0, 1)
    trousers = TROUSER_COLOURS[rng.integers(len(TROUSER_COLOURS))]
    return skin, hair, shirt, trousers


def build_pedestrian(
    rng: np.random.Generator, length: float, width: float, height: float, owner: int
) -> Primitives:
    """A walking person: head (face and hair), torso, swinging arms with hands, striding legs
    with shoes. The stride spans `length`, shoulders and arms `width`, head top `height`."""
    builder = ShapeBuilder()
    skin, hair, shirt, trousers = _person_colours(rng)
    scale = height / 1.76
    head_radii = np.array([0.1, 0.085, 0.12]) * scale
    head_z = height - head_radii[2]
    builder.ellipsoid((0.0, 0.0, head_z), head_radii, mat.HEAD, skin, hair)
    shoulder_z = head_z - head_radii[2] - 0.06 * scale
    hip_z = 0.53 * height
    shoulder_half = np.clip(width / 2 - 0.1, 0.14, 0.24)
    builder.box(
        (-0.11 * scale, -shoulder_half, hip_z - 0.05),
        (0.11 * scale, shoulder_half, shoulder_z),
        mat.CLOTH,
        shirt,
    )
    builder.box(
        (-0.1 * scale, -shoulder_half * 0.8, hip_z - 0.12),
        (0.1 * scale, shoulder_half * 0.8, hip_z + 0.02),
        mat.CLOTH,
        trousers,
    )
    stride = np.clip((length - 0.28) / 2, 0.0, 0.45)
    arm_y = min(width / 2 - 0.045, shoulder_half + 0.05)
    arm_length = 0.36 * height
    for side, phase in ((-1.0, 1.0), (1.0, -1.0)):
        hand_x = phase * min(0.55 * stride + 0.05, 0.3)
        hand = (hand_x, side * arm_y, shoulder_z - np.sqrt(max(arm_length**2 - hand_x**2, 0.01)))
        builder.segment((0.0, side * arm_y, shoulder_z), hand, 0.045, 0.05, mat.ARM, shirt, skin)
        foot_x = -phase * stride
        foot = (foot_x, side * 0.1 * scale, 0.08)
        builder.segment((0.0, side * 0.1 * scale, hip_z), foot, 0.07, 0.075, mat.CLOTH, trousers)
        builder.box(
            (foot_x - 0.1, side * 0.1 * scale - 0.055, 0.0),
            (foot_x + 0.14, side * 0.1 * scale + 0.055, 0.1),
            mat.CLOTH,
            np.array([0.1, 0.09, 0.09]),
        )
    return builder.build(owner)


@dataclass(frozen=True)
class Bicycle:
    """Where a built bicycle's parts are (object frame): a rider's hips sit above the seat,
    hands on the bar's grips at +-grip_y, feet on the pedals around the crank."""

    crank: tuple[float, float, float]
    seat: tuple[float, float, float]
    bar: tuple[float, float, float]
    grip_y: float


def build_bicycle(
    builder: ShapeBuilder, rng: np.random.Generator, length: float, width: float, y: float = 0.0
) -> Bicycle:
    """Two wheels, frame, handlebar and maybe a rear rack with panniers, centred at (0, y)."""
    frame_colour = np.clip(SHIRT_COLOURS[rng.integers(len(SHIRT_COLOURS))] * 0.6, 0, 1)
    tyre = np.array([0.06, 0.06, 0.06])
    radius = np.clip(length / 5.2, 0.28, 0.36)
    rear, front = -length / 2 + radius, length / 2 - radius
    for wx in (rear, front):
        builder.wheel((wx, y, radius), radius, 0.025, mat.TYRE, tyre)
    crank = (rear + 0.42 * (front - rear), y, radius * 0.95)
    seat = (rear + 0.25 * (front - rear), y, radius + 0.55)
    bar = (front - 0.12, y, radius + 0.68)
    for a, b in (
        ((rear, y, radius), crank),
        ((rear, y, radius), seat),
        (seat, crank),
        (crank, bar),
        (seat, bar),
        (bar, (front, y, radius)),
    ):
        builder.segment(a, b, 0.022, 0.022, mat.BIKE, frame_colour)
    grip_y = max(width / 2 - 0.05, 0.2)
    if rng.random() < 0.6:  # rear rack with panniers
        bag = np.clip(TROUSER_COLOURS[rng.integers(len(TROUSER_COLOURS))] * 0.8, 0, 1)
        rack_z = 2 * radius + 0.04
        builder.box(
            (rear - 0.2, y - 0.08, rack_z - 0.03),
            (rear + 0.2, y + 0.08, rack_z),
            mat.BIKE,
            frame_colour,
        )
        for side in (-1.0, 1.0):
            inner, outer = side * 0.08, side * min(grip_y - 0.02, 0.24)
            builder.box(
                (rear - 0.22, y + min(inner, outer), rack_z - 0.38),
                (rear + 0.16, y + max(inner, outer), rack_z),
                mat.CLOTH,
                bag,
            )
    builder.segment(
        (bar[0], y - grip_y, bar[2]), (bar[0], y + grip_y, bar[2]), 0.018, 0.018, mat.BIKE, tyre
    )
    return Bicycle(crank, seat, bar, grip_y)


def build_cyclist(
    rng: np.random.Generator, length: float, width: float, height: float, owner: int
) -> Primitives:
    """A bicycle (two wheels, frame, handlebar) with a rider leaning forward."""
    builder = ShapeBuilder()
    skin, hair, shirt, trousers = _person_colours(rng)
    if rng.random() < 0.5:
        hair = np.clip(SHIRT_COLOURS[rng.integers(len(SHIRT_COLOURS))], 0, 1)  # a helmet
    bike = build_bicycle(builder, rng, length, width)
    crank, seat, bar, grip_y = bike.crank, bike.seat, bike.bar, bike.grip_y
    scale = height / 1.74
    head_radii = np.array([0.1, 0.085, 0.12]) * scale
    head = (bar[0] - 0.2, 0.0, height - head_radii[2])
    builder.ellipsoid(head, head_radii, mat.HEAD, skin, hair)
    hip = (seat[0] - 0.02, 0.0, seat[2] + 0.08)
    shoulder = (head[0] - 0.08, 0.0, head[2] - head_radii[2] - 0.08 * scale)
    builder.segment(hip, shoulder, 0.18, 0.11, mat.CLOTH, shirt)
    for side, crank_angle in ((-1.0, 0.6), (1.0, 0.6 + np.pi)):
        pedal = (
            crank[0] + 0.17 * np.cos(crank_angle),
            side * 0.12,
            crank[2] + 0.17 * np.sin(crank_angle),
        )
        knee = ((hip[0] + pedal[0]) / 2 + 0.2, side * 0.17, (hip[2] + pedal[2]) / 2 + 0.1)
        builder.segment((hip[0], side * 0.1, hip[2]), knee, 0.07, 0.07, mat.CLOTH, trousers)
        builder.segment(knee, pedal, 0.055, 0.055, mat.CLOTH, trousers)
        builder.segment(
            (shoulder[0], side * 0.17, shoulder[2]),
            (bar[0], side * grip_y, bar[2] + 0.03),
            0.04,
            0.045,
            mat.ARM,
            shirt,
            skin,
        )
    return builder.build(owner)
