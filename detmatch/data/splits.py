"""Labeled / unlabeled splits of a data set's train frames, written as ImageSets files, and the
labeled `dev` split that every tuning decision is made on (docs/design.md section 5).

With a dev fraction, the dev frames are drawn first from the source split by their own seed
(the same dev frames for every labeled split seed), and the labeled and unlabeled frames come
from the rest: dev is disjoint from the labeled subset, the unlabeled pool and val.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detmatch.data.kitti import KittiDataset, write_image_set

# The dev frames' permutation seed: fixed, so all labeled split seeds share one dev split.
DEV_SEED = 1000


@dataclass(frozen=True)
class SplitResult:
    labeled_path: Path
    unlabeled_path: Path
    num_labeled: int
    num_unlabeled: int
    dev_path: Path | None = None
    num_dev: int = 0


def split_names(
    fraction: float, seed: int, source_split: str = "train", dev_fraction: float = 0.0
) -> tuple[str, str]:
    """ImageSets names (without .txt) of the labeled and unlabeled halves of a split."""
    tag = f"{fraction:g}_s{seed}" + (f"_dev{dev_fraction:g}" if dev_fraction else "")
    return f"{source_split}_labeled_{tag}", f"{source_split}_unlabeled_{tag}"


def dev_name(dev_fraction: float, source_split: str = "train") -> str:
    """ImageSets name of the dev split held out of source_split."""
    return f"{source_split}_dev{dev_fraction:g}"


def choose_labeled(ids: list[str], fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """Split ids into (labeled, unlabeled), both sorted.

    The labeled set is a prefix of one seeded permutation, so for one seed a smaller fraction's
    labeled frames are a subset of a larger fraction's. At least one frame is labeled, and at
    least one is unlabeled when there are two or more.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    if not ids:
        raise ValueError("cannot split an empty list of frames")
    order = np.random.default_rng(seed).permutation(len(ids))
    count = int(round(fraction * len(ids)))
    count = min(max(count, 1), max(len(ids) - 1, 1))
    chosen = set(order[:count].tolist())
    labeled = sorted(ids[i] for i in range(len(ids)) if i in chosen)
    unlabeled = sorted(ids[i] for i in range(len(ids)) if i not in chosen)
    return labeled, unlabeled


def make_split(
    data_root: Path,
    fraction: float,
    seed: int,
    source_split: str = "train",
    dev_fraction: float = 0.0,
) -> SplitResult:
    """Write ImageSets/{source}_labeled_{fraction}_s{seed}.txt and its unlabeled complement.

    fraction is of the source split's frames. With dev_fraction > 0, first hold out
    ImageSets/{source}_dev{dev_fraction}.txt (that fraction of the source, the same for every
    seed) and draw the labeled and unlabeled frames from the rest (names end _dev{fraction})."""
    for name, value in (("fraction", fraction), ("dev_fraction", dev_fraction)):
        if not 0.0 <= value < 1.0 or (name == "fraction" and value == 0.0):
            raise ValueError(f"{name} must be in {'(0, 1)' if name == 'fraction' else '[0, 1)'}, "
                             f"got {value}")  # fmt: skip
    dataset = KittiDataset(data_root)
    ids = dataset.ids(source_split)
    dev_path, dev = None, []
    pool = ids
    if dev_fraction:
        dev, pool = choose_labeled(ids, dev_fraction, DEV_SEED)
    if not pool:
        raise ValueError(
            f"--dev-fraction {dev_fraction} holds out all {len(ids)} frames of "
            f"'{source_split}': none is left to split"
        )
    labeled, unlabeled = choose_labeled(pool, min(fraction * len(ids) / len(pool), 0.999), seed)
    if not unlabeled:
        raise ValueError(
            f"--fraction {fraction} with --dev-fraction {dev_fraction} of the {len(ids)} frames "
            f"of '{source_split}' leaves no unlabeled frame ({len(dev)} dev, {len(labeled)} "
            "labeled): lower one of them"
        )
    if dev_fraction:
        dev_path = dataset.image_set_path(dev_name(dev_fraction, source_split))
        write_image_set(dev_path, dev)
    labeled_name, unlabeled_name = split_names(fraction, seed, source_split, dev_fraction)
    labeled_path = dataset.image_set_path(labeled_name)
    unlabeled_path = dataset.image_set_path(unlabeled_name)
    write_image_set(labeled_path, labeled)
    write_image_set(unlabeled_path, unlabeled)
    return SplitResult(
        labeled_path, unlabeled_path, len(labeled), len(unlabeled), dev_path, len(dev)
    )
