"""Ray casting against boxes, cylinders and ellipsoids, vectorised over (ray, primitive) pairs.

Every primitive is an affine image of a unit shape: the cube [-1, 1]^3, the cylinder
x^2 + y^2 <= 1, |z| <= 1, or the unit sphere. A primitive stores its centre, a rotation whose
columns are its local axes in the world (LiDAR) frame, and its half sizes along those axes.
A ray o + t d maps to unit space as A (o - c) + t A d with A = S^-1 R^T, so the ray parameter t
(metres along a unit world direction) is the same in both spaces.

A sensor decides which rays may meet a primitive (a window of rows and columns of its ray
grid, from the primitive's projected bounds); only those pairs are tested.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BOX, CYLINDER, ELLIPSOID = 0, 1, 2
MIN_HIT_DISTANCE = 1e-3
PAIR_CHUNK = 262_144


@dataclass(frozen=True)
class Primitives:
    """P primitives in the world (LiDAR) frame, metres.

    kind: (P,) BOX / CYLINDER / ELLIPSOID; center: (P, 3); rotation: (P, 3, 3), columns are the
    local axes (a cylinder's axis is local z); half_size: (P, 3) along the local axes;
    material: (P,) material ids (see shading); colour: (P, 3) and colour2: (P, 3) RGB in [0, 1]
    (colour2 is a material's second colour: hair, hands, roof, window frames);
    owner: (P,) index of the scene object the primitive belongs to.
    """

    kind: np.ndarray
    center: np.ndarray
    rotation: np.ndarray
    half_size: np.ndarray
    material: np.ndarray
    colour: np.ndarray
    colour2: np.ndarray
    owner: np.ndarray

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    @property
    def world_to_unit(self) -> np.ndarray:
        """(P, 3, 3) A = S^-1 R^T, mapping world offsets from the centre to unit space."""
        return np.transpose(self.rotation, (0, 2, 1)) / self.half_size[:, :, None]

    def bounding_corners(self) -> np.ndarray:
        """(P, 8, 3) corners of each primitive's oriented bounding box, world frame."""
        signs = np.array(
            [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
        )
        local = signs[None] * self.half_size[:, None, :]
        return np.einsum("pij,pkj->pki", self.rotation, local) + self.center[:, None, :]


def concatenate_primitives(parts: list[Primitives]) -> Primitives:
    """Join primitive sets in order."""
    return Primitives(
        *(np.concatenate([getattr(p, name) for p in parts]) for name in Primitives.__annotations__)
    )


@dataclass(frozen=True)
class RayHits:
    """Every (ray, primitive) intersection found: ray (H,) ray index, prim (H,), t (H,) metres."""

    ray: np.ndarray
    prim: np.ndarray
    t: np.ndarray


def window_pairs(
    windows: np.ndarray, num_columns: int, wrap_columns: bool
) -> tuple[np.ndarray, np.ndarray]:
    """(P, 4) windows row0, row1, col0, col1 (half-open) -> (ray index (K,), primitive (K,)).

    Rays are numbered row * num_columns + column. With wrap_columns, columns are taken modulo
    num_columns (a spinning LiDAR's azimuth); otherwise windows must lie inside the grid.
    Pairs come grouped by primitive, in primitive order.
    """
    windows = np.asarray(windows, dtype=np.int64)
    rows = np.clip(windows[:, 1] - windows[:, 0], 0, None)
    cols = np.clip(windows[:, 3] - windows[:, 2], 0, None)
    counts = rows * cols
    total = int(counts.sum())
    prim = np.repeat(np.arange(len(windows)), counts)
    if total == 0:
        return np.zeros(0, dtype=np.int64), prim
    starts = np.cumsum(counts) - counts
    offset = np.arange(total) - np.repeat(starts, counts)
    width = np.repeat(np.maximum(cols, 1), counts)
    row = np.repeat(windows[:, 0], counts) + offset // width
    col = np.repeat(windows[:, 2], counts) + offset % width
    if wrap_columns:
        col %= num_columns
    return row * num_columns + col, prim


def _intersect_unit(kind: int, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit-space origins (K, 3), directions (K, 3) -> (entry t (K,), unit normal (K, 3)).

    t is +inf where the ray misses or starts inside the shape.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if kind == BOX:
            inverse = 1.0 / d
            t1 = (-1.0 - o) * inverse
            t2 = (1.0 - o) * inverse
            near = np.minimum(t1, t2)
            axis = np.argmax(near, axis=1)
            t_near = np.take_along_axis(near, axis[:, None], 1)[:, 0]
            t_far = np.maximum(t1, t2).min(axis=1)
            hit = (t_near <= t_far) & (t_near > MIN_HIT_DISTANCE)
            normal = np.zeros_like(o)
            sign = -np.sign(np.take_along_axis(d, axis[:, None], 1)[:, 0])
            normal[np.arange(len(o)), axis] = sign
        elif kind == ELLIPSOID:
            a = np.einsum("ki,ki->k", d, d)
            b = np.einsum("ki,ki->k", o, d)
            c = np.einsum("ki,ki->k", o, o) - 1.0
            disc = b * b - a * c
            t_near = (-b - np.sqrt(disc)) / a
            hit = (disc >= 0) & (t_near > MIN_HIT_DISTANCE)
            normal = o + t_near[:, None] * d
        else:
            a = d[:, 0] ** 2 + d[:, 1] ** 2
            b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
            c = o[:, 0] ** 2 + o[:, 1] ** 2 - 1.0
            disc = b * b - a * c
            t_side = (-b - np.sqrt(disc)) / a
            z_side = o[:, 2] + t_side * d[:, 2]
            side_ok = (disc >= 0) & (t_side > MIN_HIT_DISTANCE) & (np.abs(z_side) <= 1.0)
            cap_z = np.where(o[:, 2] > 0, 1.0, -1.0)
            t_cap = (cap_z - o[:, 2]) / d[:, 2]
            x_cap = o[:, 0] + t_cap * d[:, 0]
            y_cap = o[:, 1] + t_cap * d[:, 1]
            cap_ok = (np.abs(o[:, 2]) > 1.0) & (t_cap > MIN_HIT_DISTANCE)
            cap_ok &= x_cap * x_cap + y_cap * y_cap <= 1.0
            t_near = np.where(side_ok, t_side, np.where(cap_ok, t_cap, np.inf))
            hit = side_ok | cap_ok
            normal = np.zeros_like(o)
            normal[:, 0] = np.where(side_ok, o[:, 0] + t_side * d[:, 0], 0.0)
            normal[:, 1] = np.where(side_ok, o[:, 1] + t_side * d[:, 1], 0.0)
            normal[:, 2] = np.where(side_ok, 0.0, cap_z)
    t = np.where(hit, t_near, np.inf)
    return t, normal


def _unit_rays(
    prims: Primitives,
    origin: np.ndarray,
    dirs: np.ndarray,
    ray: np.ndarray,
    prim: np.ndarray,
    world_to_unit: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    a = world_to_unit[prim]
    o_unit = np.einsum("pij,pj->pi", world_to_unit, origin[None, :] - prims.center)[prim]
    d = dirs[ray]
    d_unit = a[:, :, 0] * d[:, 0:1] + a[:, :, 1] * d[:, 1:2] + a[:, :, 2] * d[:, 2:3]
    return o_unit, d_unit


def cast_pairs(
    prims: Primitives,
    origin: np.ndarray,
    dirs: np.ndarray,
    ray: np.ndarray,
    prim: np.ndarray,
    max_distance: float = np.inf,
) -> RayHits:
    """Test the given (ray, primitive) pairs; keep the hits.

    origin: (3,) shared ray origin; dirs: (R, 3) unit directions, world frame.
    """
    world_to_unit = prims.world_to_unit
    kinds = prims.kind[prim]
    found_ray, found_prim, found_t = [], [], []
    for kind in (BOX, CYLINDER, ELLIPSOID):
        selected = np.flatnonzero(kinds == kind)
        for start in range(0, selected.size, PAIR_CHUNK):
            chunk = selected[start : start + PAIR_CHUNK]
            o_unit, d_unit = _unit_rays(prims, origin, dirs, ray[chunk], prim[chunk], world_to_unit)
            t, _ = _intersect_unit(kind, o_unit, d_unit)
            keep = t <= max_distance
            found_ray.append(ray[chunk][keep])
            found_prim.append(prim[chunk][keep])
            found_t.append(t[keep])
    if not found_ray:
        return RayHits(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    return RayHits(np.concatenate(found_ray), np.concatenate(found_prim), np.concatenate(found_t))


def nearest_hits(hits: RayHits, num_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """Per ray, the nearest hit: (t (R,) metres, +inf for none; primitive (R,), -1 for none).

    Ties go to the lower primitive index, so the result does not depend on pair order.
    """
    t_near = np.full(num_rays, np.inf)
    np.minimum.at(t_near, hits.ray, hits.t)
    winner = hits.t == t_near[hits.ray]
    prim_near = np.full(num_rays, np.iinfo(np.int64).max)
    np.minimum.at(prim_near, hits.ray[winner], hits.prim[winner])
    prim_near[~np.isfinite(t_near)] = -1
    return t_near, prim_near


def surface_at(
    prims: Primitives, origin: np.ndarray, dirs: np.ndarray, ray: np.ndarray, prim: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface data where rays meet given primitives (pairs known to hit).

    Returns (t (K,) metres, unit-space hit point (K, 3) in [-1, 1], world unit normal (K, 3)).
    """
    world_to_unit = prims.world_to_unit
    t = np.full(len(ray), np.inf)
    unit_point = np.zeros((len(ray), 3))
    normal = np.zeros((len(ray), 3))
    for kind in (BOX, CYLINDER, ELLIPSOID):
        selected = np.flatnonzero(prims.kind[prim] == kind)
        if selected.size == 0:
            continue
        o_unit, d_unit = _unit_rays(
            prims, origin, dirs, ray[selected], prim[selected], world_to_unit
        )
        t_k, n_unit = _intersect_unit(kind, o_unit, d_unit)
        t[selected] = t_k
        unit_point[selected] = o_unit + np.where(np.isfinite(t_k), t_k, 0.0)[:, None] * d_unit
        # Normals go back to the world by A^T = R S^-1.
        a = world_to_unit[prim[selected]]
        n_world = np.einsum("kji,kj->ki", a, n_unit)
        normal[selected] = n_world / np.maximum(
            np.linalg.norm(n_world, axis=1, keepdims=True), 1e-12
        )
    return t, unit_point, normal
