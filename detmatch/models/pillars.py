"""Point cloud -> pillars, in numpy: the one voxelisation used by training and by serving.

It imports no torch, so the labeling service runs exactly this function before onnxruntime.
`Pillars` is the one record of pillarized input: one frame's numpy arrays from `pillarize`,
or a batch's tensors (`detmatch.data.dataset.collate_pillars`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

# Per-point pillar features: x, y, z, intensity, offsets to the pillar's point mean (3) and to
# the pillar's centre (2) -- PointPillars' nine.
PILLAR_FEATURES = 9


@dataclass(frozen=True)
class PillarGrid:
    """A bird's-eye-view grid over point_cloud_range (x_min, y_min, z_min, x_max, y_max, z_max)
    in metres, LiDAR frame, with square-ish pillars of pillar_size (dx, dy) metres."""

    point_cloud_range: tuple[float, ...]
    pillar_size: tuple[float, float]
    max_points_per_pillar: int
    max_pillars: int

    def __post_init__(self) -> None:
        if len(self.point_cloud_range) != 6:
            raise ValueError(f"point_cloud_range needs 6 values, got {self.point_cloud_range}")
        x_min, y_min, z_min, x_max, y_max, z_max = self.point_cloud_range
        if not (x_max > x_min and y_max > y_min and z_max > z_min):
            raise ValueError(f"point_cloud_range is empty: {self.point_cloud_range}")
        if min(self.pillar_size) <= 0:
            raise ValueError(f"pillar_size must be positive, got {self.pillar_size}")
        for name, (extent, step) in {
            "x": (x_max - x_min, self.pillar_size[0]),
            "y": (y_max - y_min, self.pillar_size[1]),
        }.items():
            cells = extent / step
            if abs(cells - round(cells)) > 1e-6:
                raise ValueError(
                    f"the {name} range ({extent} m) is not a multiple of the pillar size {step}"
                )

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) cells."""
        x_min, y_min, _, x_max, y_max, _ = self.point_cloud_range
        return (
            int(round((y_max - y_min) / self.pillar_size[1])),
            int(round((x_max - x_min) / self.pillar_size[0])),
        )


@dataclass(frozen=True)
class Pillars:
    """Pillarized LiDAR input: features (P, M, 9) float32, zero beyond each pillar's points;
    coords (P, 2) int64 (iy, ix) cells of one frame, or (P, 3) (frame, iy, ix) of a batch;
    counts (P,) int64 points per pillar in [1, M]; batch_size: frames (1 for one frame).

    numpy arrays for one frame (what `pillarize` returns and the labeler feeds onnxruntime),
    torch tensors for a batch. `batch_pillars` makes frames' arrays the exported 3D graph's inputs.
    """

    features: Any
    coords: Any
    counts: Any
    batch_size: int = 1

    def __post_init__(self) -> None:
        pillars = len(self.features)
        if len(self.coords) != pillars or len(self.counts) != pillars:
            raise ValueError(
                f"Pillars: {pillars} features, {len(self.coords)} coords, {len(self.counts)} counts"
            )

    def __len__(self) -> int:
        return len(self.features)

    @property
    def arrays(self) -> tuple[Any, Any, Any]:
        """(features, coords, counts): the 3D graph's inputs."""
        return self.features, self.coords, self.counts

    def to(self, device: Any) -> Pillars:
        """A batch's tensors on device."""
        return dataclasses.replace(
            self,
            features=self.features.to(device, non_blocking=True),
            coords=self.coords.to(device, non_blocking=True),
            counts=self.counts.to(device, non_blocking=True),
        )


def batch_pillars(frames: Sequence[Pillars]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames' pillars (each `pillarize`'s) -> the exported 3D graph's batched inputs:
    features (B, P, M, 9) float32, coords (B, P, 2) int64, num_points (B, P) int64, P the
    most pillars of any frame. A frame with fewer repeats its last pillar up to P: the same
    feature scattered onto the same cell again, so its canvas, and its detections, are
    unchanged. A frame with no pillar gets one with zero points at cell (0, 0), which scatters
    a zero feature: exactly the empty canvas (the graph needs at least one pillar). A batch
    of one is a view of its frame's arrays, without a copy."""
    if not frames:
        raise ValueError("batch_pillars: no frames")
    frames = [f if len(f) else _empty_pillar(f.features.shape[1]) for f in frames]
    if len(frames) == 1:
        return tuple(np.asarray(a)[None] for a in frames[0].arrays)
    width = max(len(f) for f in frames)
    features = np.empty((len(frames), width, *frames[0].features.shape[1:]), np.float32)
    coords = np.empty((len(frames), width, 2), np.int64)
    counts = np.empty((len(frames), width), np.int64)
    for i, frame in enumerate(frames):
        n = len(frame)
        for out, array in zip((features, coords, counts), frame.arrays, strict=True):
            out[i, :n] = array
            out[i, n:] = array[n - 1]
    return features, coords, counts


def _empty_pillar(max_points: int) -> Pillars:
    return Pillars(
        np.zeros((1, max_points, PILLAR_FEATURES), np.float32),
        np.zeros((1, 2), dtype=np.int64),
        np.zeros(1, dtype=np.int64),
    )


def pillarize(points: np.ndarray, grid: PillarGrid) -> Pillars:
    """(N, 4) LiDAR points -> one frame's pillars.

    Returns features (P, M, 9) float32 (zero beyond each pillar's points), coords (P, 2) int64
    (iy, ix) cells, and counts (P,) int64 in [1, M]. Points outside the range are dropped;
    a pillar keeps its first M points in input order; when more than max_pillars are occupied,
    the fullest are kept. Pillars come out in row-major cell order. Deterministic.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must be (N, 4), got {points.shape}")
    x_min, y_min, z_min, x_max, y_max, z_max = grid.point_cloud_range
    ny, nx = grid.shape
    max_points = grid.max_points_per_pillar
    inside = np.flatnonzero(
        (points[:, 0] >= x_min)
        & (points[:, 0] < x_max)
        & (points[:, 1] >= y_min)
        & (points[:, 1] < y_max)
        & (points[:, 2] >= z_min)
        & (points[:, 2] < z_max)
    )
    ix = np.clip(((points[inside, 0] - x_min) / grid.pillar_size[0]).astype(np.int64), 0, nx - 1)
    iy = np.clip(((points[inside, 1] - y_min) / grid.pillar_size[1]).astype(np.int64), 0, ny - 1)
    cell = iy * nx + ix
    # Stable order by cell (a pillar keeps its first points in input order): NumPy sorts
    # 16-bit keys by radix, about twice as fast as int64 keys on a 64-beam sweep.
    order = np.argsort(cell.astype(np.uint16) if ny * nx <= 1 << 16 else cell, kind="stable")
    cell = cell[order]
    # The sorted cells' runs (what np.unique would give, without sorting them again).
    starts = np.flatnonzero(np.concatenate(([cell.size > 0], cell[1:] != cell[:-1])))
    occupied = cell[starts]
    counts = np.diff(np.append(starts, cell.size))
    if occupied.size > grid.max_pillars:
        fullest = np.sort(np.argsort(-counts, kind="stable")[: grid.max_pillars])
        occupied, starts, counts = occupied[fullest], starts[fullest], counts[fullest]
    num_pillars = occupied.size
    kept = np.minimum(counts, max_points)

    # Position of each kept point: pillar p, slot s < kept[p]; gathered once from the input.
    pillar_of_slot = np.repeat(np.arange(num_pillars), kept)
    slot = np.arange(pillar_of_slot.size) - np.repeat(np.cumsum(kept) - kept, kept)
    kept_points = points[inside[order[starts[pillar_of_slot] + slot]]]

    sums = np.stack(
        [
            np.bincount(pillar_of_slot, weights=kept_points[:, k], minlength=num_pillars)
            for k in range(3)
        ],
        axis=1,
    )
    means = (sums / np.maximum(kept, 1)[:, None]).astype(np.float32)
    coords = np.stack([occupied // nx, occupied % nx], axis=1).astype(np.int64)
    centre_x = (coords[:, 1].astype(np.float32) + 0.5) * grid.pillar_size[0] + x_min
    centre_y = (coords[:, 0].astype(np.float32) + 0.5) * grid.pillar_size[1] + y_min
    # Each kept point's 9 features as one row, written with one scatter of whole rows.
    rows = np.empty((kept_points.shape[0], PILLAR_FEATURES), dtype=np.float32)
    rows[:, :4] = kept_points
    rows[:, 4:7] = kept_points[:, :3] - means[pillar_of_slot]
    rows[:, 7] = kept_points[:, 0] - centre_x[pillar_of_slot]
    rows[:, 8] = kept_points[:, 1] - centre_y[pillar_of_slot]
    features = np.zeros((num_pillars, max_points, PILLAR_FEATURES), dtype=np.float32)
    features.reshape(-1, PILLAR_FEATURES)[pillar_of_slot * max_points + slot] = rows
    return Pillars(features, coords, kept.astype(np.int64))
