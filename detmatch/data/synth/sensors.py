"""The sensor rig: KITTI's camera 2 calibration and an HDL-64E-like spinning LiDAR.

World frame = LiDAR frame (x forward, y left, z up, metres). The road plane lies at
z = -LIDAR_HEIGHT; the camera centre follows from the calibration (about 1.65 m above the road,
0.27 m ahead of the LiDAR), as on KITTI's recording car.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detmatch.structures import Calibration

LIDAR_HEIGHT = 1.73
GROUND_Z = -LIDAR_HEIGHT

# KITTI training frame 000001 (drive 2011_09_26): camera 2 projection, rectification and
# LiDAR -> camera extrinsics.
KITTI_P2 = np.array(
    [
        [7.215377e02, 0.0, 6.095593e02, 4.485728e01],
        [0.0, 7.215377e02, 1.728540e02, 2.163791e-01],
        [0.0, 0.0, 1.0, 2.745884e-03],
    ]
)
KITTI_R0_RECT = np.array(
    [
        [9.999239e-01, 9.837760e-03, -7.445048e-03],
        [-9.869795e-03, 9.999421e-01, -4.278459e-03],
        [7.402527e-03, 4.351614e-03, 9.999631e-01],
    ]
)
KITTI_TR_VELO_TO_CAM = np.array(
    [
        [7.533745e-03, -9.999714e-01, -6.166020e-04, -4.069766e-03],
        [1.480249e-02, 7.280733e-04, -9.998902e-01, -7.631618e-02],
        [9.998621e-01, 7.523790e-03, 1.480755e-02, -2.717806e-01],
    ]
)
# (width, height, scale of P2's first two rows)
RESOLUTIONS = {"full": (1242, 375, 1.0), "half": (621, 188, 0.5)}


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera 2 of the rig. width, height in pixels; pixel (col, row) centres sit at
    integer image coordinates u = col, v = row."""

    calib: Calibration
    width: int
    height: int

    @property
    def scale(self) -> float:
        """Pixels per full-resolution pixel (1.0 full, 0.5 half)."""
        return self.width / RESOLUTIONS["full"][0]

    @property
    def origin(self) -> np.ndarray:
        """(3,) camera centre in the LiDAR frame."""
        projection = self.calib.lidar_to_image
        return -np.linalg.solve(projection[:, :3], projection[:, 3])

    def directions(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(N,) image coordinates -> (N, 3) unit LiDAR-frame ray directions."""
        inverse = np.linalg.inv(self.calib.lidar_to_image[:, :3])
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        dirs = np.stack(
            [inverse[i, 0] * u + inverse[i, 1] * v + inverse[i, 2] for i in range(3)], axis=-1
        )
        return dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)

    def pixel_directions(self) -> np.ndarray:
        """(H * W, 3) ray directions of every pixel, row-major."""
        rows, cols = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        return self.directions(cols.ravel(), rows.ravel())

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) LiDAR points -> ((..., 2) u, v; (...,) depth along the optical axis)."""
        projection = self.calib.lidar_to_image
        p = np.asarray(points, dtype=np.float64)
        homogeneous = np.einsum("...j,ij->...i", p, projection[:, :3]) + projection[:, 3]
        depth = homogeneous[..., 2]
        safe = np.where(np.abs(depth) < 1e-9, 1e-9, depth)
        return homogeneous[..., :2] / safe[..., None], depth


def make_calibration(resolution: str) -> Calibration:
    """KITTI calibration for "full" (1242x375) or "half" (621x188, P2 rows 0 and 1 halved)."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {sorted(RESOLUTIONS)}, got {resolution!r}")
    p2 = KITTI_P2.copy()
    p2[:2] *= RESOLUTIONS[resolution][2]
    return Calibration(p2, KITTI_R0_RECT.copy(), KITTI_TR_VELO_TO_CAM.copy())


def make_camera(resolution: str) -> CameraModel:
    """The camera for "full" or "half" resolution."""
    calib = make_calibration(resolution)
    width, height, _ = RESOLUTIONS[resolution]
    return CameraModel(calib, width, height)


@dataclass(frozen=True)
class LidarModel:
    """A 64-beam spinning LiDAR at the LiDAR-frame origin.

    elevations: (64,) beam elevations in radians, descending (row 0 is the top beam);
    columns: azimuth steps over 360 degrees, column j looking at azimuth
    pi - (j + 0.5) * 2 pi / columns (counter-clockwise from +x is positive azimuth);
    max_range, range_noise in metres; dropout: base probability of a lost return.
    """

    elevations: np.ndarray
    columns: int = 2000
    max_range: float = 100.0
    range_noise: float = 0.02
    dropout: float = 0.04

    @property
    def azimuth_step(self) -> float:
        return 2.0 * np.pi / self.columns

    def column_azimuths(self) -> np.ndarray:
        """(columns,) azimuth of each column in radians, decreasing from +pi."""
        return np.pi - (np.arange(self.columns) + 0.5) * self.azimuth_step

    def directions(self) -> np.ndarray:
        """(64 * columns, 3) unit beam directions, row-major (beam, column)."""
        elevation = self.elevations[:, None]
        azimuth = self.column_azimuths()[None, :]
        dirs = np.stack(
            np.broadcast_arrays(
                np.cos(elevation) * np.cos(azimuth),
                np.cos(elevation) * np.sin(azimuth),
                np.sin(elevation),
            ),
            axis=-1,
        )
        return dirs.reshape(-1, 3)


def hdl64_elevations() -> np.ndarray:
    """(64,) HDL-64E-like beam elevations in radians: upper block +2 to -8.33 degrees in 1/3
    degree steps, lower block -8.87 to -24.8 degrees in about 1/2 degree steps."""
    upper = 2.0 - np.arange(32) / 3.0
    lower = np.linspace(-8.87, -24.8, 32)
    return np.deg2rad(np.concatenate([upper, lower]))


def make_lidar() -> LidarModel:
    return LidarModel(elevations=hdl64_elevations())
