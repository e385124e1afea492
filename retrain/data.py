"""The frames of a retraining round, gathered into one KITTI-layout directory.

    ROUND/training/{image_2,velodyne,calib,label_2}/ID.*   the original data set's frames
                                                           (symbolic links) and copies of
                                                           every stored frame, as store-ID
    ROUND/ImageSets/round_labeled.txt     the original labeled frames ([data] train_split)
    ROUND/ImageSets/round_unlabeled.txt   the original unlabeled pool ([ssl] unlabeled_split)
                                          and the stored frames
    ROUND/ImageSets/round_gate.txt        the held-out gate frames ([data] val_split)

A stored frame a reviewer corrected in CVAT (`detmatch review import`, a 3D review) joins
round_labeled with the reviewer's labels as its label_2, whatever stored_labels says; `[retrain]
reviewed_gate_fraction` of them (by a hash of the key) join round_gate instead. A review is part
of the store's snapshot, so a new review makes a new round. Label Studio reviews (2D boxes only)
leave their frame where it was.

With `[retrain] stored_labels = "labeled"` the stored frames join round_labeled instead, their
stored labels (the KITTI rows of `STORE/.../label_2`) being fixed training targets. The store
is read through `serving.store.export_store` (every shard); a stored frame whose point cloud is
byte-identical to a gate frame's is left out, so the gate stays held out even when the gate's
frames were sent to the service.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from detmatch.data.kitti import FRAME_ID_PATTERN, KittiDataset, write_image_set, write_objects
from detmatch.files import sha256_file
from retrain.snapshot import frame_digest, snapshot_id, stored_digests
from serving.manifest import RoundData
from serving.reviews import has_3d_review, human_label_rows, read_human_labels
from serving.store import export_store
from serving.store_export import EXPORT_MANIFEST, Store, split_of

# The ImageSets names inside a round's data directory.
LABELED_SPLIT = "round_labeled"
UNLABELED_SPLIT = "round_unlabeled"
GATE_SPLIT = "round_gate"
# Stored frames are renamed so that they never collide with the original data set's ids.
STORED_PREFIX = "store-"
FRAME_KINDS = ("image_2", "velodyne", "calib", "label_2")
EXPORT_DIR = ".store_export"


@dataclass(frozen=True)
class SourceSplits:
    """ImageSets names of the original data set: its labeled frames, its unlabeled pool and the
    held-out gate."""

    labeled: str
    unlabeled: str
    gate: str


def stored_frame_id(exported_id: str) -> str:
    """The round's id of a stored frame: store-ID, or a digest of ID when that is too long."""
    name = f"{STORED_PREFIX}{exported_id}"
    if FRAME_ID_PATTERN.match(name):
        return name
    return STORED_PREFIX + hashlib.sha256(exported_id.encode()).hexdigest()[:40]


def compose_round_data(
    data_root: str | os.PathLike,
    store_root: Store,
    out: str | os.PathLike,
    sources: SourceSplits,
    stored_labels: str = "pool",
    progress: bool = True,
    reviewed_gate_fraction: float = 0.0,
) -> RoundData:
    """Write the round's data directory `out` (replacing whatever is there; see the module
    docstring) and return what went into it."""
    data_root, out = Path(data_root), Path(out)
    original = KittiDataset(data_root, "training")
    labeled = original.ids(sources.labeled)
    unlabeled = original.ids(sources.unlabeled)
    gate = original.ids(sources.gate)
    _check_splits(data_root, sources, labeled, unlabeled, gate)
    frames = sorted(set(labeled) | set(unlabeled) | set(gate))
    original.check_frames(frames)
    missing = [i for i in (*labeled, *gate) if not original.label_path(i).is_file()]
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} labeled or gate frames of {data_root} have no label file, e.g. "
            f"{original.label_path(missing[0])}"
        )
    if out.exists():
        shutil.rmtree(out)
    training = out / "training"
    for kind in FRAME_KINDS:
        (training / kind).mkdir(parents=True)
    for frame_id in frames:
        for kind, source in _frame_files(original, frame_id).items():
            os.symlink(source.resolve(), training / kind / source.name)
    gate_clouds = {sha256_file(original.points_path(i)) for i in gate}
    imported = _import_store(
        store_root, out, gate_clouds, set(frames), progress, reviewed_gate_fraction
    )
    stored = imported.machine
    with_labels = stored_labels == "labeled"
    write_image_set(
        out / "ImageSets" / f"{LABELED_SPLIT}.txt",
        labeled + imported.reviewed + (stored if with_labels else []),
    )
    write_image_set(
        out / "ImageSets" / f"{UNLABELED_SPLIT}.txt", unlabeled + ([] if with_labels else stored)
    )
    write_image_set(out / "ImageSets" / f"{GATE_SPLIT}.txt", gate + imported.reviewed_gate)
    excluded, snapshot = imported.excluded, imported.snapshot
    return RoundData(
        labeled=len(labeled),
        unlabeled=len(unlabeled),
        stored=len(stored),
        reviewed=len(imported.reviewed) + len(imported.reviewed_gate),
        reviewed_gate=len(imported.reviewed_gate),
        gate=len(gate) + len(imported.reviewed_gate),
        excluded=excluded,
        store_snapshot=snapshot,
        stored_labels=stored_labels,
        data_root=str(data_root.resolve()),
        splits={"labeled": sources.labeled, "unlabeled": sources.unlabeled, "gate": sources.gate},
    )


def _check_splits(
    root: Path, sources: SourceSplits, labeled: list[str], unlabeled: list[str], gate: list[str]
) -> None:
    if not labeled:
        raise ValueError(f"the labeled split {sources.labeled!r} of {root} has no frames")
    if not gate:
        raise ValueError(f"the gate split {sources.gate!r} of {root} has no frames")
    for name, ids, key in (
        (sources.labeled, labeled, "[data] train_split"),
        (sources.unlabeled, unlabeled, "[ssl] unlabeled_split"),
    ):
        shared = sorted(set(ids) & set(gate))
        if shared:
            raise ValueError(
                f"the gate split {sources.gate!r} ([data] val_split) shares {len(shared)} frames "
                f"with {name!r} ({key}) of {root}, e.g. {shared[0]}: a round's gate must be "
                "held out from its training frames"
            )


def _frame_files(dataset: KittiDataset, frame_id: str) -> dict[str, Path]:
    """kind -> file of a frame (label_2 only where the frame has one)."""
    files = {
        "image_2": dataset.image_path(frame_id),
        "velodyne": dataset.points_path(frame_id),
        "calib": dataset.calib_path(frame_id),
    }
    if dataset.label_path(frame_id).is_file():
        files["label_2"] = dataset.label_path(frame_id)
    return files


@dataclass(frozen=True)
class ImportedStore:
    """The stored frames a round took, by round id: machine-labeled ones, human-reviewed ones
    (3D reviews: labeled frames) and reviewed ones held out in the gate; the number left out
    as copies of gate frames; the snapshot id of everything read."""

    machine: list[str]
    reviewed: list[str]
    reviewed_gate: list[str]
    excluded: int
    snapshot: str


def _import_store(
    store: Store,
    out: Path,
    gate_clouds: set[str],
    taken: set[str],
    progress: bool,
    reviewed_gate_fraction: float = 0.0,
) -> ImportedStore:
    """Export every stored frame and move it into out under its round id; a frame with a 3D
    human review gets the reviewer's labels as its label_2 and joins the labeled frames (or,
    by a hash of its key, the gate)."""
    export = out / EXPORT_DIR
    export_store(store, export)
    exported = []
    if (export / "training" / "image_2").is_dir():
        exported = KittiDataset(export).ids()
    keys = {e["id"]: (e["namespace"], e["frame_id"])
            for e in json.loads((export / EXPORT_MANIFEST).read_text())["frames"]}  # fmt: skip
    reviews = read_human_labels(store)
    machine, reviewed, reviewed_gate, digests, excluded = [], [], [], [], 0
    dataset = KittiDataset(export) if exported else None
    for frame_id in tqdm(exported, desc="label store", disable=not progress, dynamic_ncols=True):
        files = _frame_files(dataset, frame_id)
        record = export / "labels" / f"{frame_id}.json"
        file_digests = {kind: sha256_file(path) for kind, path in files.items()}
        if record.is_file():
            file_digests["labels"] = sha256_file(record)
        review = reviews.get(keys[frame_id])
        digests.append(frame_digest(stored_digests(file_digests.values(), review)))
        if file_digests["velodyne"] in gate_clouds:
            excluded += 1
            continue
        name = stored_frame_id(frame_id)
        if name in taken:
            raise ValueError(f"stored frame {frame_id} would be {name}, an id the data set has")
        for kind, path in files.items():
            os.replace(path, out / "training" / kind / f"{name}{path.suffix}")
        if review is None or not has_3d_review(review):
            machine.append(name)
            continue
        frame = KittiDataset(out).load_frame(name, with_labels=False)
        rows = human_label_rows(review, frame.calib, frame.image.shape[1::-1])
        write_objects(out / "training" / "label_2" / f"{name}.txt", rows)
        side = split_of(*keys[frame_id], reviewed_gate_fraction)
        (reviewed_gate if side == "val" else reviewed).append(name)
    shutil.rmtree(export)
    return ImportedStore(machine, reviewed, reviewed_gate, excluded, snapshot_id(digests))
