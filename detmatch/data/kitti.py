"""Reading and writing the KITTI object layout.

    ROOT/ImageSets/{train,val,...}.txt
    ROOT/training/{image_2/ID.png, velodyne/ID.bin, calib/ID.txt, label_2/ID.txt}
    ROOT/testing/{image_2/ID.png, velodyne/ID.bin, calib/ID.txt}

as KITTI's object benchmark ships it. Images may be PNG or JPEG (image_2/ID.png, .jpg or
.jpeg); this project writes PNG.

Label and result files are KITTI's 15 (labels) or 16 (results: + score) columns per object:
type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y [score], camera frame, bottom
centre. They are converted to the project's LiDAR-frame boxes here and nowhere else.
Malformed files raise KittiFormatError naming the file, the line and the problem.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from detmatch.files import atomic_write_bytes
from detmatch.geometry import kitti_camera_to_lidar_boxes, lidar_to_kitti_camera_boxes
from detmatch.structures import Boxes2D, Boxes3D, Calibration, Frame, Labels

FRAME_ID_PATTERN = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")
# KITTI's subset directories: training/ (with label_2) and testing/ (without).
SUBSETS = ("training", "testing")
# Image files a frame may have, in the order they are looked for.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
CALIB_SIZES = {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "R0_rect": 9, "Tr_velo_to_cam": 12,
               "Tr_imu_to_velo": 12}  # fmt: skip
# KITTI's placeholder 3D fields for objects without a 3D box (DontCare, 2D-only results).
PLACEHOLDER_DIMENSIONS = (-1.0, -1.0, -1.0)
PLACEHOLDER_LOCATION = (-1000.0, -1000.0, -1000.0)
PLACEHOLDER_ROTATION = -10.0


class KittiFormatError(ValueError):
    """A KITTI file that cannot be read: names the file, the line (1-based) and the problem."""

    def __init__(self, path: str | os.PathLike, line: int | None, problem: str) -> None:
        where = f"{path}:{line}" if line is not None else str(path)
        super().__init__(f"{where}: {problem}")
        self.path = str(path)
        self.line = line
        self.problem = problem


def validate_frame_id(frame_id: str) -> str:
    """Frame ids are file stems: letters, digits, '_' and '-', at most 64 characters."""
    if not isinstance(frame_id, str) or not FRAME_ID_PATTERN.match(frame_id):
        raise ValueError(f"invalid frame id {frame_id!r}: use 1-64 letters, digits, '_' or '-'")
    return frame_id


@dataclass(frozen=True)
class KittiObjects:
    """The rows of one KITTI label or result file, as written: rectified camera frame.

    names (N,); truncated (N,); occluded (N,) int; alpha (N,); bbox (N, 4) x1 y1 x2 y2;
    dimensions (N, 3) h w l; location (N, 3) bottom centre x y z; rotation_y (N,);
    score (N,) or None for label files.
    """

    names: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: np.ndarray | slice) -> KittiObjects:
        return KittiObjects(
            names=self.names[index],
            truncated=self.truncated[index],
            occluded=self.occluded[index],
            alpha=self.alpha[index],
            bbox=self.bbox[index],
            dimensions=self.dimensions[index],
            location=self.location[index],
            rotation_y=self.rotation_y[index],
            score=None if self.score is None else self.score[index],
        )

    @property
    def has_3d(self) -> np.ndarray:
        """(N,) bool: the row carries a real 3D box, not KITTI's placeholder fields."""
        return np.all(self.dimensions > 0, axis=1) & (self.location[:, 1] > -999.0)

    @staticmethod
    def empty(with_score: bool = False) -> KittiObjects:
        return KittiObjects(
            names=np.zeros(0, dtype=object),
            truncated=np.zeros(0),
            occluded=np.zeros(0, dtype=np.int64),
            alpha=np.zeros(0),
            bbox=np.zeros((0, 4)),
            dimensions=np.zeros((0, 3)),
            location=np.zeros((0, 3)),
            rotation_y=np.zeros(0),
            score=np.zeros(0) if with_score else None,
        )


def parse_objects(text: str, path: str | os.PathLike = "<text>") -> KittiObjects:
    """Parse label (15 columns) or result (16 columns) text. All rows must agree."""
    rows: list[list[float]] = []
    names: list[str] = []
    columns: int | None = None
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (15, 16):
            raise KittiFormatError(path, number, f"expected 15 or 16 fields, found {len(fields)}")
        if columns is None:
            columns = len(fields)
        elif len(fields) != columns:
            raise KittiFormatError(
                path, number, f"found {len(fields)} fields where earlier lines had {columns}"
            )
        try:
            values = [float(v) for v in fields[1:]]
        except ValueError as error:
            raise KittiFormatError(path, number, f"non-numeric field: {error}") from None
        if not all(math.isfinite(v) for v in values):
            raise KittiFormatError(path, number, "NaN or Inf in a numeric field")
        if values[1] != int(values[1]):
            raise KittiFormatError(path, number, f"occluded must be an integer, got {fields[2]}")
        names.append(fields[0])
        rows.append(values)
    if not rows:
        return KittiObjects.empty(with_score=False)
    table = np.array(rows, dtype=np.float64)
    return KittiObjects(
        names=np.array(names, dtype=object),
        truncated=table[:, 0],
        occluded=table[:, 1].astype(np.int64),
        alpha=table[:, 2],
        bbox=table[:, 3:7],
        dimensions=table[:, 7:10],
        location=table[:, 10:13],
        rotation_y=table[:, 13],
        score=table[:, 14] if columns == 16 else None,
    )


def format_objects(objects: KittiObjects, decimals: int = 2) -> str:
    """KITTI text for the rows; scores (result files) get four decimals."""
    lines = []
    f = f"{{:.{decimals}f}}"
    for i in range(len(objects)):
        fields = [
            str(objects.names[i]),
            f.format(objects.truncated[i]),
            str(int(objects.occluded[i])),
            f.format(objects.alpha[i]),
            *(f.format(v) for v in objects.bbox[i]),
            *(f.format(v) for v in objects.dimensions[i]),
            *(f.format(v) for v in objects.location[i]),
            f.format(objects.rotation_y[i]),
        ]
        if objects.score is not None:
            fields.append(f"{objects.score[i]:.4f}")
        lines.append(" ".join(fields))
    return "".join(line + "\n" for line in lines)


def read_objects(path: str | os.PathLike) -> KittiObjects:
    return parse_objects(_read_text(path), path)


def write_objects(path: str | os.PathLike, objects: KittiObjects, decimals: int = 2) -> None:
    atomic_write_bytes(path, format_objects(objects, decimals).encode())


def objects_to_labels(objects: KittiObjects, calib: Calibration) -> Labels:
    """File rows -> project Labels: 3D boxes into the LiDAR frame (placeholder rows -> zeros)."""
    boxes = np.zeros((len(objects), 7))
    real = objects.has_3d
    if real.any():
        boxes[real] = kitti_camera_to_lidar_boxes(
            objects.location[real], objects.dimensions[real], objects.rotation_y[real], calib
        )
    return Labels(
        names=objects.names,
        boxes_2d=Boxes2D(objects.bbox),
        boxes_3d=Boxes3D(boxes),
        truncated=objects.truncated,
        occluded=objects.occluded,
        alpha=objects.alpha,
        scores=objects.score,
    )


def labels_to_objects(
    labels: Labels, calib: Calibration, has_3d: np.ndarray | None = None
) -> KittiObjects:
    """Project Labels -> file rows. Rows where has_3d is False (default: DontCare rows and boxes
    of zero size) get KITTI's placeholder 3D fields."""
    n = len(labels)
    if has_3d is None:
        has_3d = (labels.names != "DontCare") & np.all(labels.boxes_3d.dims > 0, axis=1)
    location = np.tile(PLACEHOLDER_LOCATION, (n, 1))
    dimensions = np.tile(PLACEHOLDER_DIMENSIONS, (n, 1))
    rotation_y = np.full(n, PLACEHOLDER_ROTATION)
    if has_3d.any():
        location[has_3d], dimensions[has_3d], rotation_y[has_3d] = lidar_to_kitti_camera_boxes(
            labels.boxes_3d.data[has_3d], calib
        )
    return KittiObjects(
        names=labels.names,
        truncated=labels.truncated,
        occluded=labels.occluded,
        alpha=labels.alpha,
        bbox=labels.boxes_2d.xyxy,
        dimensions=dimensions,
        location=location,
        rotation_y=rotation_y,
        score=labels.scores,
    )


# ---------------------------------------------------------------------------------------------
# Calibration, points, images, image sets


def read_calib_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every matrix of a KITTI calib file, flat, by key (P0..P3, R0_rect, Tr_velo_to_cam, ...)."""
    matrices: dict[str, np.ndarray] = {}
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise KittiFormatError(path, number, "expected 'KEY: numbers'")
        key = key.strip()
        try:
            values = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError as error:
            raise KittiFormatError(path, number, f"non-numeric value for {key}: {error}") from None
        expected = CALIB_SIZES.get(key)
        if expected is not None and values.size != expected:
            raise KittiFormatError(
                path, number, f"{key} needs {expected} numbers, found {values.size}"
            )
        if not np.all(np.isfinite(values)):
            raise KittiFormatError(path, number, f"NaN or Inf in {key}")
        matrices[key] = values
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        if key not in matrices:
            raise KittiFormatError(path, None, f"missing {key}")
    return matrices


def read_calib(path: str | os.PathLike) -> Calibration:
    m = read_calib_file(path)
    return Calibration.from_flat(m["P2"], m["R0_rect"], m["Tr_velo_to_cam"])


def write_calib(
    path: str | os.PathLike, calib: Calibration, extra: Mapping[str, np.ndarray] | None = None
) -> None:
    """Write a KITTI calib file. Keys KITTI tools expect but `calib` lacks (P0, P1, P3,
    Tr_imu_to_velo) come from `extra`, else P0 = P1 = P3 = P2 and Tr_imu_to_velo = identity."""
    identity = np.eye(4)[:3].reshape(-1)
    matrices = {
        "P0": calib.P2.reshape(-1),
        "P1": calib.P2.reshape(-1),
        "P2": calib.P2.reshape(-1),
        "P3": calib.P2.reshape(-1),
        "R0_rect": calib.R0_rect.reshape(-1),
        "Tr_velo_to_cam": calib.Tr_velo_to_cam.reshape(-1),
        "Tr_imu_to_velo": identity,
    }
    for key, value in (extra or {}).items():
        if key not in ("P2", "R0_rect", "Tr_velo_to_cam"):
            matrices[key] = np.asarray(value, dtype=np.float64).reshape(-1)
    text = "".join(
        f"{key}: {' '.join(f'{v:.12e}' for v in value)}\n" for key, value in matrices.items()
    )
    atomic_write_bytes(path, text.encode())


def read_points(path: str | os.PathLike) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity from a little-endian float32 .bin file."""
    raw = Path(path).read_bytes()
    if len(raw) % 16:
        raise KittiFormatError(
            path, None, f"size {len(raw)} bytes is not a multiple of 16 (N x 4 float32)"
        )
    points = np.frombuffer(raw, dtype="<f4").reshape(-1, 4).astype(np.float32)
    if not np.all(np.isfinite(points)):
        raise KittiFormatError(path, None, "NaN or Inf in the point cloud")
    return points


def write_points(path: str | os.PathLike, points: np.ndarray) -> None:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must be (N, 4), got {points.shape}")
    atomic_write_bytes(path, points.astype("<f4").tobytes())


def read_image(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8 RGB."""
    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"))
    except (OSError, SyntaxError) as error:
        raise KittiFormatError(path, None, f"cannot decode image: {error}") from None


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB as PNG (deterministic bytes for the same pixels)."""
    import io

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8), mode="RGB").save(
        buffer, format="PNG", compress_level=6
    )
    atomic_write_bytes(path, buffer.getvalue())


def read_image_set(path: str | os.PathLike) -> list[str]:
    ids = []
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        frame_id = line.strip()
        if not frame_id:
            continue
        if not FRAME_ID_PATTERN.match(frame_id):
            raise KittiFormatError(path, number, f"invalid frame id {frame_id!r}")
        ids.append(frame_id)
    return ids


def write_image_set(path: str | os.PathLike, ids: list[str]) -> None:
    for frame_id in ids:
        validate_frame_id(frame_id)
    atomic_write_bytes(path, "".join(f"{i}\n" for i in ids).encode())


def _read_text(path: str | os.PathLike) -> str:
    try:
        return Path(path).read_text()
    except UnicodeDecodeError as error:
        raise KittiFormatError(path, None, f"not text: {error}") from None


# ---------------------------------------------------------------------------------------------
# The data set


def find_subset(root: str | os.PathLike) -> str:
    """The subset directory to read when none is named: training/ if root has one, else
    testing/ (a stock KITTI download has both)."""
    root = Path(root)
    for subset in SUBSETS:
        if (root / subset).is_dir():
            return subset
    hint = ""
    if (root / "image_2").is_dir():
        hint = f"; {root} looks like a subset directory itself: pass its parent"
    raise FileNotFoundError(
        f"{root} has neither training/ nor testing/ (KITTI layout expected){hint}"
    )


class KittiDataset:
    """A KITTI-layout data set rooted at `root` (the directory holding ImageSets/ and the
    subset directory split_dir: training/ or testing/)."""

    def __init__(self, root: str | os.PathLike, split_dir: str = "training") -> None:
        self.root = Path(root)
        self.split_dir = split_dir
        if not (self.root / split_dir).is_dir():
            raise FileNotFoundError(
                f"{self.root} has no {split_dir}/ directory (KITTI layout expected)"
            )

    def _path(self, kind: str, frame_id: str, suffix: str) -> Path:
        return self.root / self.split_dir / kind / f"{validate_frame_id(frame_id)}{suffix}"

    def image_path(self, frame_id: str) -> Path:
        """image_2/ID.png, or the frame's JPEG (.jpg, .jpeg) when there is no PNG; the PNG's
        name when the frame has no image at all."""
        for suffix in IMAGE_SUFFIXES:
            path = self._path("image_2", frame_id, suffix)
            if path.is_file():
                return path
        return self._path("image_2", frame_id, ".png")

    def points_path(self, frame_id: str) -> Path:
        return self._path("velodyne", frame_id, ".bin")

    def calib_path(self, frame_id: str) -> Path:
        return self._path("calib", frame_id, ".txt")

    def label_path(self, frame_id: str) -> Path:
        return self._path("label_2", frame_id, ".txt")

    def image_set_path(self, split: str) -> Path:
        return self.root / "ImageSets" / f"{split}.txt"

    def ids(self, split: str | None = None) -> list[str]:
        """Frame ids of an ImageSets split, or every frame with an image (PNG or JPEG) when split
        is None. An image whose name is not a valid frame id is an error naming it."""
        if split is not None:
            path = self.image_set_path(split)
            if not path.exists():
                available = sorted(p.stem for p in (self.root / "ImageSets").glob("*.txt"))
                raise FileNotFoundError(f"no split {split!r} at {path}; available: {available}")
            return read_image_set(path)
        images = self.root / self.split_dir / "image_2"
        if not images.is_dir():
            raise FileNotFoundError(f"{images} does not exist (KITTI layout expected)")
        ids = set()
        for path in images.iterdir():
            if path.suffix in IMAGE_SUFFIXES:
                if not FRAME_ID_PATTERN.match(path.stem):
                    raise KittiFormatError(path, None, f"invalid frame id {path.stem!r}")
                ids.add(path.stem)
        return sorted(ids)

    def check_frames(self, frame_ids: list[str]) -> None:
        """FileNotFoundError naming the missing files (the first five) unless every frame has
        its image, point cloud and calibration."""
        missing = []
        for frame_id in frame_ids:
            for path in (
                self.image_path(frame_id),
                self.points_path(frame_id),
                self.calib_path(frame_id),
            ):
                if not path.is_file():
                    missing.append(str(path))
        if missing:
            more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            raise FileNotFoundError(
                f"{len(missing)} frame files are missing: {', '.join(missing[:5])}{more}"
            )

    def read_objects(self, frame_id: str) -> KittiObjects:
        return read_objects(self.label_path(frame_id))

    def load_frame(self, frame_id: str, with_labels: bool = True) -> Frame:
        calib = read_calib(self.calib_path(frame_id))
        labels = None
        if with_labels and self.label_path(frame_id).exists():
            labels = objects_to_labels(self.read_objects(frame_id), calib)
        return Frame(
            frame_id=frame_id,
            image=read_image(self.image_path(frame_id)),
            points=read_points(self.points_path(frame_id)),
            calib=calib,
            labels=labels,
        )


def write_frame(root: str | os.PathLike, frame: Frame, split_dir: str = "training") -> None:
    """Write one frame's four files into a KITTI layout under root."""
    base = Path(root) / split_dir
    frame_id = validate_frame_id(frame.frame_id)
    write_image(base / "image_2" / f"{frame_id}.png", frame.image)
    write_points(base / "velodyne" / f"{frame_id}.bin", frame.points)
    write_calib(base / "calib" / f"{frame_id}.txt", frame.calib)
    if frame.labels is not None:
        write_objects(
            base / "label_2" / f"{frame_id}.txt", labels_to_objects(frame.labels, frame.calib)
        )
