"""Which frames a command reads (`detmatch label`, `predict`): an ImageSets split, the ids of a
file, or every frame with an image, from KITTI's training/ or testing/ directory.

A stock KITTI download has no ImageSets, and its testing/ frames have no labels; both work:
`FrameSelection(all_frames=True, subset="testing")`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from detmatch.data.kitti import SUBSETS, KittiDataset, find_subset, read_image_set


@dataclass(frozen=True)
class FrameSelection:
    """Exactly one of split (an ImageSets name), ids_file (frame ids, one a line) or all_frames
    (every frame with an image); subset: training or testing (None: training/ if the data set
    has one, else testing/)."""

    split: str | None = None
    ids_file: Path | None = None
    all_frames: bool = False
    subset: str | None = None

    def __post_init__(self) -> None:
        chosen = (self.split is not None) + (self.ids_file is not None) + bool(self.all_frames)
        if chosen != 1:
            raise ValueError("choose frames with exactly one of a split, an ids file or all frames")
        if self.subset is not None and self.subset not in SUBSETS:
            raise ValueError(f"subset must be one of {', '.join(SUBSETS)}, got {self.subset!r}")

    def describe(self) -> str:
        if self.split is not None:
            return f"split {self.split!r}"
        if self.ids_file is not None:
            return f"the ids of {self.ids_file}"
        return "all frames"

    def resolve(self, root: str | os.PathLike) -> tuple[KittiDataset, list[str]]:
        """The data set and the selected frame ids, after checking that every frame has its
        image, point cloud and calibration (FileNotFoundError naming the missing files)."""
        dataset = KittiDataset(root, self.subset or find_subset(root))
        if self.split is not None:
            if not (dataset.root / "ImageSets").is_dir():
                raise FileNotFoundError(
                    f"{dataset.root} has no ImageSets/ for split {self.split!r}: select frames "
                    "with --all (every frame) or --ids-file FILE instead"
                )
            ids = dataset.ids(self.split)
        elif self.ids_file is not None:
            ids = read_image_set(self.ids_file)
        else:
            ids = dataset.ids()
        if not ids:
            raise ValueError(f"{self.describe()} of {Path(root) / dataset.split_dir} has no frames")
        dataset.check_frames(ids)
        return dataset, ids
