"""Sampling a road scene: road, lighting, parked rows, traffic, pedestrians, cyclists, clutter
and roadside background, each placed only where its footprint is free.

Distances: road users from about 30 m behind to 85 m ahead (the LiDAR sees all around, the
camera ahead); background from 45 m behind to 200 m ahead.
"""

from __future__ import annotations

import numpy as np

from detmatch.data.synth import scenery, shapes
from detmatch.data.synth.primitives import Primitives, concatenate_primitives
from detmatch.data.synth.scene import (
    CLASS_SIZES,
    SIZE_LIMITS,
    Lighting,
    RoadLayout,
    Scene,
    SceneObject,
    frame_rng,
)
from detmatch.data.synth.sensors import GROUND_Z
from detmatch.data.synth.world import DEFAULT_WORLD, WORLDS, World
from detmatch.geometry import paired_bev_intersection

# The recording car around the LiDAR: nothing may stand there. (x, y, z, l, w, h, yaw)
EGO_BOX = np.array([-0.6, 0.0, GROUND_Z + 0.8, 6.0, 2.6, 1.6, 0.0])
CURB = 0.25
_BUILDERS = {
    "Car": shapes.build_car,
    "Van": shapes.build_van,
    "Pedestrian": shapes.build_pedestrian,
    "Cyclist": shapes.build_cyclist,
}


class Placer:
    """Builds objects and keeps those whose footprint is free, while one scene is sampled."""

    def __init__(self, rng: np.random.Generator, road: RoadLayout) -> None:
        self.rng = rng
        self.road = road
        self.objects: list[SceneObject] = []
        self.prims: list[Primitives] = []
        self.footprints: list[np.ndarray] = [EGO_BOX]

    def free(self, box: np.ndarray, margin: float) -> bool:
        """Whether the (7,) box grown by margin metres meets no placed footprint."""
        grown = box.copy()
        grown[3:5] += 2 * margin
        others = np.array(self.footprints)
        reach = 0.5 * np.hypot(others[:, 3], others[:, 4]) + 0.5 * np.hypot(grown[3], grown[4])
        near = np.hypot(others[:, 0] - box[0], others[:, 1] - box[1]) < reach
        if not near.any():
            return True
        areas = paired_bev_intersection(np.repeat(grown[None], near.sum(), 0), others[near])
        return bool(np.all(areas <= 0.0))

    def place(
        self,
        kind: str,
        prims: Primitives,
        s: float,
        u: float,
        yaw: float,
        margin: float = 0.15,
        round_shadow: bool = False,
    ) -> bool:
        """Put object-frame prims at road position (s, u) with heading yaw relative to the
        road; False (nothing placed) if the spot is taken."""
        x, y = self.road.to_world(s, u)
        placed, box = shapes.place(prims, float(x), float(y), yaw + self.road.heading, GROUND_Z)
        if not self.free(box, margin):
            return False
        self.objects.append(SceneObject(kind, box, round_shadow))
        self.prims.append(placed)
        self.footprints.append(box)
        return True

    @property
    def owner(self) -> int:
        """Index the next placed object will get."""
        return len(self.objects)

    def scene(self, lighting: Lighting, texture_seed: int) -> Scene:
        """The scene of everything placed so far."""
        return Scene(
            objects=tuple(self.objects),
            primitives=concatenate_primitives(self.prims),
            road=self.road,
            lighting=lighting,
            texture_seed=texture_seed,
        )

    def road_user(self, kind: str) -> Primitives:
        """Object-frame primitives of a Car, Van, Pedestrian or Cyclist of KITTI-like size."""
        mean, spread = CLASS_SIZES[kind]
        low, high = SIZE_LIMITS[kind]
        size = np.clip(self.rng.normal(mean, spread), low, high)
        return _BUILDERS[kind](self.rng, *(float(v) for v in size), self.owner)


def sample_lighting(rng: np.random.Generator) -> Lighting:
    elevation = np.deg2rad(rng.uniform(22, 60))
    azimuth = rng.uniform(-np.pi, np.pi)
    sun = np.array(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ]
    )
    haze = rng.uniform(0.0, 1.0)
    sky_top = np.array([0.40, 0.56, 0.86]) * (1 - 0.6 * haze) + 0.6 * haze * np.array(
        [0.86, 0.89, 0.93]
    )
    sky_horizon = np.clip(np.array([0.82, 0.87, 0.93]) * rng.uniform(0.95, 1.06), 0, 1)
    return Lighting(
        sun, float(rng.uniform(0.38, 0.5)), float(rng.uniform(0.55, 0.75)), sky_top, sky_horizon
    )


def sample_road(rng: np.random.Generator) -> RoadLayout:
    lane_width = rng.uniform(3.0, 3.6)
    lanes_forward = int(rng.integers(1, 3))
    lanes_backward = int(rng.integers(1, 3))
    lanes_right, lanes_left = -lanes_forward * lane_width, lanes_backward * lane_width
    parking_right = rng.uniform(2.1, 2.5) if rng.random() < 0.75 else 0.4
    parking_left = rng.uniform(2.1, 2.5) if rng.random() < 0.6 else 0.4
    ego_lane = int(rng.integers(lanes_forward))
    urban = rng.random() < 0.75
    return RoadLayout(
        heading=float(np.clip(rng.normal(0, 0.03), -0.08, 0.08)),
        ego_offset=float(-(ego_lane + 0.5) * lane_width + rng.normal(0, 0.2)),
        lane_width=float(lane_width),
        lanes_left=float(lanes_left),
        lanes_right=float(lanes_right),
        road_left=float(lanes_left + parking_left),
        road_right=float(lanes_right - parking_right),
        sidewalk_left=float(rng.uniform(1.8, 4.0)) if urban or rng.random() < 0.4 else 0.0,
        sidewalk_right=float(rng.uniform(1.8, 4.0)) if urban or rng.random() < 0.4 else 0.0,
    )


def _edges(road: RoadLayout, side: int) -> tuple[float, float]:
    """(u of the asphalt edge, u of the sidewalk's outer edge) on side +1 (left) / -1 (right)."""
    edge = road.road_left if side > 0 else road.road_right
    walk = road.sidewalk_left if side > 0 else road.sidewalk_right
    return edge, edge + side * (CURB + walk)


def place_parked_rows(placer: Placer) -> None:
    """Rows of cars parked bumper to bumper (gaps 0.5-2 m) in the parking strips: they overlap
    heavily in the image while standing apart in 3D."""
    rng, road = placer.rng, placer.road
    for side in (1, -1):
        edge = road.road_left if side > 0 else road.road_right
        lanes = road.lanes_left if side > 0 else road.lanes_right
        if abs(edge - lanes) < 2.0 or rng.random() > 0.85:
            continue
        s = rng.uniform(-25.0, 12.0)
        end = s + rng.uniform(30.0, 75.0)
        facing = 0.0 if side < 0 or rng.random() < 0.4 else np.pi
        while s < end:
            kind = "Van" if rng.random() < 0.1 else "Car"
            prims = placer.road_user(kind)
            low, high = shapes.local_extent(prims)
            length, width = high[0] - low[0], high[1] - low[1]
            u = edge - side * (width / 2 + rng.uniform(0.15, 0.4))
            placer.place(kind, prims, s + length / 2, u, facing + rng.normal(0, 0.025), margin=0.1)
            s += length + rng.uniform(0.5, 2.0)
            if rng.random() < 0.08:
                s += rng.uniform(4.0, 9.0)


def place_road_users(placer: Placer, world: World) -> None:
    """Traffic in the lanes (mostly along the road, some turning), pedestrians on the
    sidewalks (alone or in groups, some crossing), cyclists at the lane edges."""
    rng, road = placer.rng, placer.road
    lanes = [
        (-(i + 0.5) * road.lane_width, 0.0)
        for i in range(round(-road.lanes_right / road.lane_width))
    ]
    lanes += [
        ((i + 0.5) * road.lane_width, np.pi)
        for i in range(round(road.lanes_left / road.lane_width))
    ]
    for u_lane, heading in lanes:
        s = rng.uniform(-35.0, 0.0)
        while s < 85.0:
            s += rng.uniform(7.0, 38.0)
            kind = "Van" if rng.random() < 0.08 else "Car"
            yaw = heading + rng.normal(0, 0.02)
            if rng.random() < 0.12:
                yaw += rng.choice([-1, 1]) * rng.uniform(0.25, 1.3)
            placer.place(
                kind, placer.road_user(kind), s, u_lane + rng.normal(0, 0.25), yaw, margin=0.3
            )

    for _ in range(int(rng.integers(*world.pedestrian_groups))):
        side = int(rng.choice([-1, 1]))
        edge, outer = _edges(road, side)
        if outer == edge + side * CURB:
            u0 = edge + side * rng.uniform(0.8, 2.5)
        else:
            u0 = rng.uniform(min(edge, outer), max(edge, outer))
        s0 = rng.uniform(-12.0, 60.0)
        yaw0 = (
            rng.uniform(-np.pi, np.pi)
            if rng.random() < 0.25
            else rng.choice([0.0, np.pi]) + rng.normal(0, 0.25)
        )
        for _ in range(int(rng.choice([1, 1, 1, 2, 2, 3]))):
            s_ped, u_ped = s0 + rng.uniform(-1.5, 1.5), u0 + rng.uniform(-0.7, 0.7)
            placer.place(
                "Pedestrian",
                placer.road_user("Pedestrian"),
                s_ped,
                u_ped,
                yaw0 + rng.normal(0, 0.15),
                0.08,
            )
    if rng.random() < 0.35:
        s, u = rng.uniform(7.0, 40.0), rng.uniform(road.lanes_right, road.lanes_left)
        yaw = rng.choice([-1, 1]) * np.pi / 2 + rng.normal(0, 0.2)
        placer.place("Pedestrian", placer.road_user("Pedestrian"), s, u, yaw, 0.1)

    for _ in range(int(rng.integers(*world.cyclists))):
        choice = rng.random()
        if choice < 0.5:
            u, yaw = road.lanes_right + rng.uniform(0.5, 0.9), 0.0
        elif choice < 0.8:
            u, yaw = road.lanes_left - rng.uniform(0.5, 0.9), np.pi
        else:
            edge, outer = _edges(road, -1)
            u, yaw = (edge + outer) / 2, rng.choice([0.0, np.pi])
        placer.place(
            "Cyclist",
            placer.road_user("Cyclist"),
            rng.uniform(-10.0, 60.0),
            u,
            yaw + rng.normal(0, 0.08),
            0.25,
        )


def place_clutter(placer: Placer, world: World) -> None:
    """Pedestrian-sized clutter on the sidewalks and verges, mostly in view ahead."""
    rng, road = placer.rng, placer.road
    for _ in range(int(rng.integers(*world.clutter_count))):
        kind = str(rng.choice(world.clutter_kinds))
        side = int(rng.choice([-1, 1]))
        edge, outer = _edges(road, side)
        if rng.random() < world.clutter_at_curb:
            u = edge + side * (CURB + rng.uniform(0.3, 0.7))
        else:
            u = outer + side * rng.uniform(-0.6, 1.2)
        s = rng.uniform(3.0, 55.0) if rng.random() < 0.8 else rng.uniform(-20.0, 80.0)
        prims = scenery.build_clutter(rng, kind, placer.owner)
        placer.place(f"clutter/{kind}", prims, s, u, rng.uniform(-np.pi, np.pi), margin=0.2)


def place_background(placer: Placer) -> None:
    """Per roadside: buildings (urban) or trees, hedges and walls (green), guardrails where
    there is no sidewalk; a second row of trees or blocks further out."""
    rng, road = placer.rng, placer.road
    for side in (1, -1):
        edge, outer = _edges(road, side)
        walk = road.sidewalk_left if side > 0 else road.sidewalk_right
        urban = walk > 0 and rng.random() < 0.8
        if walk == 0:
            s = -40.0
            while s < 120.0:
                length = 16.0
                rail = scenery.build_guardrail(rng, length, placer.owner)
                placer.place("guardrail", rail, s + length / 2, edge + side * 0.6, 0.0, margin=0.05)
                s += length + 0.2
        if walk > 0 and rng.random() < 0.5:
            for s in np.arange(rng.uniform(-40, -30), 150.0, rng.uniform(8.0, 16.0)):
                tree = scenery.build_tree(rng, placer.owner)
                placer.place(
                    "tree", tree, s, outer - side * 0.6, 0.0, margin=0.1, round_shadow=True
                )
        s = -45.0
        setback = outer + side * rng.uniform(0.5, 6.0)
        while s < 200.0:
            if urban:
                length, depth = rng.uniform(8.0, 22.0), rng.uniform(8.0, 14.0)
                block = scenery.build_building(
                    rng, length, depth, rng.uniform(5.0, 19.0), placer.owner
                )
                u = setback + side * (depth / 2 + rng.uniform(0.0, 2.5))
                placer.place("building", block, s + length / 2, u, 0.0, margin=0.2)
                s += length + (rng.uniform(0.0, 8.0) if rng.random() < 0.6 else 0.2)
            else:
                choice = rng.random()
                if choice < 0.5:
                    tree = scenery.build_tree(rng, placer.owner)
                    u = setback + side * rng.uniform(1.0, 4.0)
                    placer.place("tree", tree, s, u, 0.0, margin=0.1, round_shadow=True)
                    s += rng.uniform(4.0, 12.0)
                else:
                    length = rng.uniform(6.0, 18.0)
                    build = scenery.build_hedge if choice < 0.8 else scenery.build_wall
                    thing = build(rng, length, placer.owner)
                    placer.place(
                        "hedge" if choice < 0.8 else "wall",
                        thing,
                        s + length / 2,
                        setback,
                        0.0,
                        0.1,
                    )
                    s += length + rng.uniform(0.5, 6.0)
        far = setback + side * rng.uniform(12.0, 25.0)
        s = -30.0
        while s < 200.0:
            if rng.random() < 0.5:
                length = rng.uniform(10.0, 22.0)
                block = scenery.build_building(
                    rng, length, 10.0, rng.uniform(8.0, 25.0), placer.owner
                )
                placer.place("building", block, s + length / 2, far + side * 5.0, 0.0, margin=0.2)
                s += length + rng.uniform(2.0, 15.0)
            else:
                tree = scenery.build_tree(rng, placer.owner)
                placer.place("tree", tree, s, far + side * rng.uniform(0.0, 6.0), 0.0, 0.1, True)
                s += rng.uniform(3.0, 10.0)


def sample_scene(seed: int, frame_index: int, world: World = WORLDS[DEFAULT_WORLD]) -> Scene:
    """The scene of frame `frame_index` of the data set made with `seed` in `world`, without
    rendering.

    Depends on (seed, frame_index, world) only (see scene.frame_rng).
    """
    rng = frame_rng(seed, frame_index)
    road = sample_road(rng)
    lighting = sample_lighting(rng)
    placer = Placer(rng, road)
    place_parked_rows(placer)
    place_road_users(placer, world)
    place_clutter(placer, world)
    place_background(placer)
    return placer.scene(lighting, int(rng.integers(2**31)))
