"""World versions: the knobs that decide how the two sensors fail, selectable and recorded.

A data set's synth.json names its world; a benchmark reads it back and reports it. "v1" is
the world every result before 2026-12-07 was measured on, and stays bit-identical. "v2"
gives the sensors KITTI's trade-off (docs/design.md section 6; BENCHMARKS.md, issue 41): in
the point cloud, people-shaped roadside things (pay stations, shrubs, parked bicycles without
riders) stand where people stand, sign faces no longer reflect like retroreflectors, and
people's dark clothing loses more returns; in the image all of them lack a person's skin,
hair and clothing colours.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType

from detmatch.data.synth import materials as mat

V1_CLUTTER = ("post", "bollard", "cabinet", "bin", "sign", "trunk")


@dataclass(frozen=True)
class World:
    """name: the version written into synth.json.
    clutter_kinds: what clutter is drawn from (uniformly); clutter_count: [low, high) per
    scene; clutter_at_curb: the share of clutter standing at the curb (the rest is set back
    on the sidewalk, where people walk).
    lidar_reflectivity / lidar_dropout: per material, overrides of materials.py's base
    reflectivity and additions to its extra dropout.
    pedestrian_groups / cyclists: [low, high) groups of pedestrians on the sidewalks and
    cyclists per scene."""

    name: str
    clutter_kinds: tuple[str, ...] = V1_CLUTTER
    clutter_count: tuple[int, int] = (5, 14)
    clutter_at_curb: float = 0.6
    lidar_reflectivity: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    lidar_dropout: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    pedestrian_groups: tuple[int, int] = (1, 6)
    cyclists: tuple[int, int] = (0, 3)


WORLDS = {
    "v1": World("v1"),
    "v2": World(
        "v2",
        clutter_kinds=V1_CLUTTER + ("pay_station", "shrub", "bicycles"),
        clutter_count=(10, 22),
        clutter_at_curb=0.4,
        lidar_reflectivity=MappingProxyType({mat.SIGN: 0.35}),
        lidar_dropout=MappingProxyType({mat.CLOTH: 0.12, mat.ARM: 0.12, mat.HEAD: 0.12}),
    ),
}
# v3: v2 with people's clothing, arms and heads losing more returns (sparser people, as a
# 64-beam sensor sees them past 20 m).
WORLDS["v3"] = replace(
    WORLDS["v2"],
    name="v3",
    lidar_dropout=MappingProxyType({mat.CLOTH: 0.22, mat.ARM: 0.22, mat.HEAD: 0.22}),
)
# The camera stand-in's world (benchmarks/camera_init.py): v3 crowded with people and
# cyclists, as COCO, the paper's 2D pre-training, is crowded with people. Never a benchmark
# world.
WORLDS["v3-crowd"] = replace(WORLDS["v3"], name="v3-crowd", pedestrian_groups=(4, 12),
                             cyclists=(2, 7))  # fmt: skip
DEFAULT_WORLD = "v1"


def get_world(name: str) -> World:
    """The world of a version name; a clear error naming the versions there are."""
    if name not in WORLDS:
        raise ValueError(f"unknown world {name!r}; choose from {sorted(WORLDS)}")
    return WORLDS[name]


def synth_record(root: Path) -> dict:
    """A data set's synth.json ({} for a data set that synth did not write)."""
    record = Path(root) / "synth.json"
    return json.loads(record.read_text()) if record.is_file() else {}


def read_world(root: Path) -> str:
    """The world version of a data set: its synth.json's "world" ("v1" for sets written
    before versions were recorded); "" for a data set that synth did not write (KITTI)."""
    record = synth_record(root)
    return str(record.get("world", "v1")) if record else ""


def read_resolution(root: Path) -> str:
    """The camera resolution a synthetic data set was rendered at ("full" or "half"); ""
    for a data set that synth did not write."""
    record = synth_record(root)
    return str(record.get("resolution", "half")) if record else ""
