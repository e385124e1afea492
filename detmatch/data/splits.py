"""Labeled / unlabeled splits of a data set's train frames, written as ImageSets files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detmatch.data.kitti import KittiDataset, write_image_set


@dataclass(frozen=True)
class SplitResult:
    labeled_path: Path
    unlabeled_path: Path
    num_labeled: int
    num_unlabeled: int


def split_names(fraction: float, seed: int, source_split: str = "train") -> tuple[str, str]:
    """ImageSets names (without .txt) of the labeled and unlabeled halves of a split."""
    tag = f"{fraction:g}_s{seed}"
    return f"{source_split}_labeled_{tag}", f"{source_split}_unlabeled_{tag}"


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
    data_root: Path, fraction: float, seed: int, source_split: str = "train"
) -> SplitResult:
    """Write ImageSets/{source}_labeled_{fraction}_s{seed}.txt and its unlabeled complement."""
    dataset = KittiDataset(data_root)
    labeled, unlabeled = choose_labeled(dataset.ids(source_split), fraction, seed)
    labeled_name, unlabeled_name = split_names(fraction, seed, source_split)
    labeled_path = dataset.image_set_path(labeled_name)
    unlabeled_path = dataset.image_set_path(unlabeled_name)
    write_image_set(labeled_path, labeled)
    write_image_set(unlabeled_path, unlabeled)
    return SplitResult(labeled_path, unlabeled_path, len(labeled), len(unlabeled))
