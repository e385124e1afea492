"""Batch labeling on Ray Data (`detmatch label --engine ray`): `label_split`'s outputs, labeled
by a pool of Ray actors, on one machine or a cluster. Torch-free; Ray is the `ray` extra.

    frames  the driver resolves the selected frames of a KITTI-layout directory (a local path,
            or a pyarrow/fsspec filesystem URL: file://, s3://, gs://, ...) as `label_split`
            does, leaves out the frames already labeled with the model version (resume,
            below) and makes the rest a Ray dataset: one row per frame, its id and the paths
            of its image, point cloud and calibration;
    label   an actor pool (`ActorPoolStrategy(size=actors)`, each actor reserving
            `cpus_per_actor` of a CPU) in which each actor loads the model version once
            (onnxruntime on one intra-op thread), reads and decodes every frame of a batch
            with the functions `detmatch label` uses (a URL's files are first fetched into a
            scratch directory of the actor) and labels it; it returns the result files' bytes
            (`serving.offline.result_files`) and, with a store, what the store keeps;
    write   the driver writes the files under OUT atomically and puts the frames into the label
            store: a store shard has one writer, so only the driver writes (its `put` and
            `get`, which every store offers).

For the same frames and model version the per-frame files and the stored frames are those of
`label_split`, byte for byte, and the LabelingSummary counts this run's labeled frames as it
does. OUT/labeling.json holds `label_split`'s fields plus the engine, the resumed count and
the failed frames.

Resume: a frame is skipped, and counted as resumed, when every output asked for already holds
it labeled by this model version: the store's record and OUT/labels/ID.json (written after
the frame's other two files). Thresholds are not compared: labeling again with other
thresholds wants a new OUT (or --overwrite) and store namespace.

Failures: a frame whose files cannot be read or decoded (an image that does not decode, a
point cloud that is not N x 16 bytes of finite floats, a calibration that does not parse) or
that the labeler refuses is logged by id with the reason as it happens, skipped, and listed in
the result and in labeling.json; the other frames are labeled. Any other error fails the run.
A killed actor is restarted and the batch it held is retried (Ray Data's defaults for actor
pools: max_restarts and max_task_retries -1); the driver gets each frame's outcome once, so
each frame is written and stored once.

Where it runs (`RayEngine.address`): None starts a local Ray instance (this process's CPUs,
loopback, no dashboard) and stops it afterwards, unless Ray is already initialised in this
process or $RAY_ADDRESS names a cluster (as inside `ray job submit`); "auto" joins the cluster
of this machine, "HOST:PORT" a cluster by its head node's GCS address. Ray Data does not run
through Ray Client (ray-project/ray#42739), so "ray://HOST:PORT" is refused with the ways that
work: submit the command as a Ray job, or run it on a node of the cluster. On a cluster the
model repository and a local --data path must be at the same path on every node (a shared
volume); OUT and the store are the driver's.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import pickle
import socket
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from detmatch.data.kitti import (
    FRAME_ID_PATTERN,
    IMAGE_SUFFIXES,
    SUBSETS,
    KittiFormatError,
    read_calib,
    read_image,
    read_image_set,
    read_points,
)
from detmatch.data.selection import FrameSelection
from detmatch.files import atomic_write_bytes
from detmatch.structures import Calibration
from serving.labeler import FrameLabels
from serving.offline import LabelingSummary, image_png, labeling_record, result_files
from serving.repository import load_manifest, served_version, verify_version, version_dir
from serving.sessions import available_cpus
from serving.store import DEFAULT_NAMESPACE, LabelStore, StoreOutcome

log = logging.getLogger(__name__)

RAY_INSTALL = "pip install 'detmatch[ray]'"
# How long the driver waits for a TCP connection to a cluster's address before giving up.
CONNECT_TIMEOUT_S = 5.0
# Test hook: a file path. The first batch any actor takes creates the file and ends its actor's
# process, so a test sees a killed actor's frames retried.
CRASH_ONCE_ENV = "DETMATCH_RAY_CRASH_ONCE"
FRAME_FILES = ("image_2", "velodyne", "calib")


class RayEngineError(ValueError):
    """Ray is not installed, or the cluster address is malformed, Ray Client's, or nothing
    answers at it."""


@dataclass(frozen=True)
class RayEngine:
    """address: see the module docstring; actors: the pool's size; batch_size: frames an actor
    takes at once; cpus_per_actor: the CPUs Ray reserves for each actor. A fraction leaves Ray
    Data's own tasks room: on a 2-CPU node, two actors at 1 CPU each starve them for ever."""

    address: str | None = None
    actors: int = 2
    batch_size: int = 8
    cpus_per_actor: float = 0.5

    def __post_init__(self) -> None:
        if self.actors < 1 or self.batch_size < 1:
            raise ValueError(
                f"actors and batch_size must be >= 1, got {self.actors} and {self.batch_size}"
            )
        if not self.cpus_per_actor > 0:
            raise ValueError(f"cpus_per_actor must be > 0, got {self.cpus_per_actor}")
        if self.address is not None:
            check_address(self.address)


@dataclass(frozen=True)
class FrameFailure:
    frame_id: str
    reason: str


@dataclass(frozen=True)
class RayLabeling:
    """summary: this run's labeled frames, counted as `label_split` counts (already_stored
    includes the resumed frames with a store); resumed: frames left as they were, labeled by
    this model version already; failed: frames that could not be read, decoded or labeled."""

    summary: LabelingSummary
    resumed: int
    failed: tuple[FrameFailure, ...]


@dataclass(frozen=True)
class FrameFiles:
    """A frame's files: local paths, or paths inside a URL's filesystem."""

    frame_id: str
    image: str
    points: str
    calib: str


@dataclass(frozen=True)
class FrameOutcome:
    """What an actor returns for a frame: an error, or its counts, result files (path
    relative to OUT -> bytes) and what the store keeps (image PNG, points, calib, labels)."""

    frame_id: str
    error: str | None = None
    labels: int = 0
    matched: int = 0
    thresholds: dict[str, float | None] | None = None
    files: dict[str, bytes] | None = None
    stored: tuple[bytes, np.ndarray, Calibration, FrameLabels] | None = None


def label_with_ray(
    repository: str | os.PathLike,
    data: str | os.PathLike,
    frames: FrameSelection,
    out_dir: str | os.PathLike | None,
    version: str | None = None,
    tau_hung: float | None = None,
    progress: bool = True,
    store: LabelStore | None = None,
    namespace: str = DEFAULT_NAMESPACE,
    engine: RayEngine = RayEngine(),  # noqa: B008 - frozen
) -> RayLabeling:
    """Label the selected frames of data (a directory or a filesystem URL) with a version of
    the model repository (default: the newest promoted one) into out_dir and/or store; see
    the module docstring."""
    if out_dir is None and store is None:
        raise ValueError("label_with_ray needs an output directory, a label store or both")
    model_dir, version = _model_version(repository, version)
    source, subset, filesystem, selected = resolve_frames(data, frames)
    out = None if out_dir is None else Path(out_dir)
    start = time.perf_counter()
    todo = [f for f in selected if not _labeled(f.frame_id, version, out, store, namespace)]
    resumed = len(selected) - len(todo)
    if resumed:
        log.info("%d of %d frames are labeled by version %s already", resumed, len(selected),
                 version)  # fmt: skip
    labeled = labels = matched = stored = 0
    failed: list[FrameFailure] = []
    thresholds: dict[str, float | None] = {}
    actor_kwargs = {"model_dir": str(model_dir), "tau_hung": tau_hung, "files": out is not None,
                    "store": store is not None, "filesystem": filesystem,
                    "crash_marker": os.environ.get(CRASH_ONCE_ENV)}  # fmt: skip
    bar = tqdm(total=len(todo), desc="label", dynamic_ncols=True, disable=not progress)
    with bar, ray_session(engine.address) if todo else contextlib.nullcontext():
        for outcome in _outcomes(todo, actor_kwargs, engine) if todo else ():
            bar.update()
            if outcome.error is not None:
                log.warning("frame %s skipped: %s", outcome.frame_id, outcome.error)
                failed.append(FrameFailure(outcome.frame_id, outcome.error))
                continue
            labeled += 1
            labels += outcome.labels
            matched += outcome.matched
            thresholds = outcome.thresholds or thresholds
            if store is not None and outcome.stored is not None:
                png, points, calib, result = outcome.stored
                put = store.put(outcome.frame_id, png, points, calib, result, namespace)
                stored += put.outcome != StoreOutcome.UNCHANGED
            for relative, content in (outcome.files or {}).items():
                atomic_write_bytes(out / relative, content)
    failed.sort(key=lambda failure: failure.frame_id)
    summary = LabelingSummary(
        frames=labeled,
        labels=labels,
        matched=matched,
        lidar_only=labels - matched,
        model_version=version,
        seconds=round(time.perf_counter() - start, 3),
        stored=stored,
        already_stored=resumed + labeled - stored if store is not None else 0,
    )
    if out is not None:
        record = labeling_record(summary, model_dir, source, subset, frames, thresholds, store)
        record.update(
            engine={"name": "ray", **asdict(engine)},
            resumed=resumed,
            failed=[asdict(failure) for failure in failed],
        )
        atomic_write_bytes(out / "labeling.json", (json.dumps(record, indent=2) + "\n").encode())
    return RayLabeling(summary, resumed, tuple(failed))


def _model_version(repository: str | os.PathLike, version: str | None) -> tuple[Path, str]:
    """The version directory and name, checked here (the actors load it again)."""
    if version is None:
        version = served_version(repository)
        if version is None:
            raise FileNotFoundError(
                f"model repository {repository} has no promoted version; promote one "
                "(detmatch-export --repository ROOT --promote VERSION) or name a version"
            )
    model_dir = version_dir(repository, version).resolve()
    manifest = load_manifest(model_dir)
    verify_version(model_dir, manifest)
    return model_dir, manifest.version


def _labeled(
    frame_id: str, version: str, out: Path | None, store: LabelStore | None, namespace: str
) -> bool:
    """Every output asked for holds the frame labeled by this version (see Resume above)."""
    if store is not None:
        record = store.get(frame_id, namespace)
        if record is None or record.model_version != version:
            return False
    if out is not None:
        try:
            record = json.loads((out / "labels" / f"{frame_id}.json").read_bytes())
        except (OSError, ValueError):
            return False
        return isinstance(record, dict) and record.get("model_version") == version
    return True


# --- the frames -----------------------------------------------------------------------------


def resolve_frames(
    data: str | os.PathLike, frames: FrameSelection
) -> tuple[str, str, Any, list[FrameFiles]]:
    """(the data set as labeling.json records it, the subset, the pyarrow filesystem of a URL
    or None for a local path, the selected frames' files), after checking that every frame has
    its three files (FileNotFoundError naming the missing ones, as `FrameSelection.resolve`)."""
    text = os.fspath(data)
    if "://" not in text:
        dataset, ids = frames.resolve(text)
        files = [
            FrameFiles(i, str(dataset.image_path(i).resolve()),
                       str(dataset.points_path(i).resolve()), str(dataset.calib_path(i).resolve()))
            for i in ids
        ]  # fmt: skip
        return str(Path(text).resolve()), dataset.split_dir, None, files
    filesystem, base = _filesystem(text)
    base = base.rstrip("/")
    subset = frames.subset or next((s for s in SUBSETS if _is_dir(filesystem, f"{base}/{s}")), "")
    if not subset or not _is_dir(filesystem, f"{base}/{subset}"):
        raise FileNotFoundError(f"{text} has no {subset or 'training/ nor testing'}/ directory "
                                "(KITTI layout expected)")  # fmt: skip
    listing = {kind: _names(filesystem, f"{base}/{subset}/{kind}") for kind in FRAME_FILES}
    images: dict[str, str] = {}
    for suffix in IMAGE_SUFFIXES:  # a PNG before a JPEG, as KittiDataset.image_path
        for name in listing["image_2"]:
            stem, found = os.path.splitext(name)
            if found == suffix:
                if frames.all_frames and not FRAME_ID_PATTERN.match(stem):
                    raise KittiFormatError(f"{text}/{subset}/image_2/{name}", None,
                                           f"invalid frame id {stem!r}")  # fmt: skip
                images.setdefault(stem, name)
    if frames.split is not None:
        ids = _image_set(filesystem, f"{base}/ImageSets/{frames.split}.txt", text)
    elif frames.ids_file is not None:
        ids = read_image_set(frames.ids_file)
    else:
        ids = sorted(images)
    if not ids:
        raise ValueError(f"{frames.describe()} of {text}/{subset} has no frames")
    names = {i: (images.get(i, f"{i}.png"), f"{i}.bin", f"{i}.txt") for i in ids}
    missing = [
        f"{text}/{subset}/{kind}/{name}"
        for frame_id in ids
        for kind, name in zip(FRAME_FILES, names[frame_id], strict=True)
        if name not in listing[kind]
    ]
    if missing:
        more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
        raise FileNotFoundError(
            f"{len(missing)} frame files are missing: {', '.join(missing[:5])}{more}"
        )
    files = [
        FrameFiles(
            i,
            *(
                f"{base}/{subset}/{kind}/{name}"
                for kind, name in zip(FRAME_FILES, names[i], strict=True)
            ),
        )
        for i in ids
    ]
    return text, subset, filesystem, files


def _filesystem(url: str) -> tuple[Any, str]:
    """pyarrow's filesystem for a URL (file://, s3://, gs://, hdfs://, ...), else fsspec's."""
    import pyarrow.fs

    try:
        return pyarrow.fs.FileSystem.from_uri(url)
    except ValueError as arrow_error:  # pyarrow.ArrowInvalid: a scheme pyarrow does not know
        try:
            import fsspec
        except ImportError:
            raise ValueError(f"--data {url}: {arrow_error}") from None
        try:
            filesystem, path = fsspec.core.url_to_fs(url)
        except (ImportError, ValueError) as error:
            raise ValueError(f"--data {url}: {error}") from None
        return pyarrow.fs.PyFileSystem(pyarrow.fs.FSSpecHandler(filesystem)), path


def _is_dir(filesystem: Any, path: str) -> bool:
    import pyarrow.fs

    return filesystem.get_file_info(path).type == pyarrow.fs.FileType.Directory


def _names(filesystem: Any, directory: str) -> set[str]:
    """The file names in a directory of the filesystem (none if it does not exist)."""
    import pyarrow.fs

    selector = pyarrow.fs.FileSelector(directory, allow_not_found=True)
    return {info.base_name for info in filesystem.get_file_info(selector) if info.is_file}


def _image_set(filesystem: Any, path: str, url: str) -> list[str]:
    """An ImageSets file's ids, checked as `read_image_set` checks them."""
    try:
        with filesystem.open_input_stream(path) as stream:
            text = stream.read().decode()
    except FileNotFoundError:
        raise FileNotFoundError(f"no split at {url}: {path} does not exist") from None
    except UnicodeDecodeError as error:
        raise KittiFormatError(path, None, f"not text: {error}") from None
    ids = []
    for number, line in enumerate(text.splitlines(), start=1):
        if line.strip() and not FRAME_ID_PATTERN.match(line.strip()):
            raise KittiFormatError(path, number, f"invalid frame id {line.strip()!r}")
        ids += [line.strip()] if line.strip() else []
    return ids


# --- the actors -----------------------------------------------------------------------------


class FrameLabeler:
    """A Ray Data actor: the model version, loaded once; labels batches of frames."""

    def __init__(
        self,
        model_dir: str,
        tau_hung: float | None,
        files: bool,
        store: bool,
        filesystem: Any,
        crash_marker: str | None,
    ) -> None:
        from serving.labeler import Labeler
        from serving.sessions import SessionSettings

        # One intra-op thread: the pool's actors are the parallelism.
        self.labeler = Labeler(model_dir, SessionSettings(intra_op_threads=1))
        self.tau_hung = tau_hung
        self.files = files
        self.store = store
        self.filesystem = filesystem
        self.crash_marker = crash_marker

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self.crash_marker is not None:
            _crash_once(self.crash_marker)
        rows = zip(batch["frame_id"], batch["image"], batch["points"], batch["calib"], strict=True)
        outcomes = [pickle.dumps(self.label(FrameFiles(*map(str, row)))) for row in rows]
        return {"frame_id": batch["frame_id"], "outcome": np.array(outcomes, dtype=object)}

    def label(self, frame: FrameFiles) -> FrameOutcome:
        """Read, decode and label one frame; an unreadable or refused frame is an error
        outcome naming the reason."""
        with self._local(frame) as (local, remote_of):
            try:
                calib = read_calib(local.calib)
                image = read_image(local.image)
                points = read_points(local.points)
                result = self.labeler.label(image, points, calib, tau_hung=self.tau_hung)
                png = image_png(Path(local.image), image) if self.store else None
            except (OSError, ValueError) as error:  # KittiFormatError is a ValueError
                reason = str(error)
                for path, original in remote_of.items():
                    reason = reason.replace(path, original)
                return FrameOutcome(frame.frame_id, error=reason)
        return FrameOutcome(
            frame.frame_id,
            labels=len(result),
            matched=int(result.labels.matched.sum()),
            thresholds=result.thresholds,
            files=result_files(frame.frame_id, result, calib) if self.files else None,
            stored=(png, points, calib, result) if png is not None else None,
        )

    @contextlib.contextmanager
    def _local(self, frame: FrameFiles) -> Iterator[tuple[FrameFiles, dict[str, str]]]:
        """The frame's files at local paths: as they are, or a URL's fetched into a scratch
        directory (removed afterwards); with {local path: the URL's path}."""
        if self.filesystem is None:
            yield frame, {}
            return
        with tempfile.TemporaryDirectory(prefix="detmatch-ray-") as scratch:
            local, remote_of = {}, {}
            for kind, path in (("image", frame.image), ("points", frame.points),
                               ("calib", frame.calib)):  # fmt: skip
                local[kind] = os.path.join(scratch, os.path.basename(path))
                remote_of[local[kind]] = path
                with self.filesystem.open_input_stream(path) as stream:
                    Path(local[kind]).write_bytes(stream.read())
            yield FrameFiles(frame.frame_id, **local), remote_of


def _crash_once(marker: str) -> None:
    """End this process if the marker file does not exist yet (creating it): CRASH_ONCE_ENV."""
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return
    os._exit(1)


# --- Ray ------------------------------------------------------------------------------------


def _outcomes(
    todo: list[FrameFiles], actor_kwargs: dict[str, Any], engine: RayEngine
) -> Iterator[FrameOutcome]:
    """The frames through the actor pool, as the outcomes arrive (in no particular order)."""
    import ray.data

    context = ray.data.DataContext.get_current()
    bars = context.enable_progress_bars
    context.enable_progress_bars = False  # the driver's own bar counts frames
    try:
        batches = math.ceil(len(todo) / engine.batch_size)
        rows = [asdict(frame) for frame in todo]
        dataset = ray.data.from_items(rows, override_num_blocks=batches).map_batches(
            FrameLabeler,
            fn_constructor_kwargs=actor_kwargs,
            batch_size=engine.batch_size,
            # No more actors (each loading the model) than there are batches to give them.
            compute=ray.data.ActorPoolStrategy(size=min(engine.actors, batches)),
            num_cpus=engine.cpus_per_actor,
            batch_format="numpy",
        )
        for row in dataset.iter_rows():
            yield pickle.loads(row["outcome"])
    finally:
        context.enable_progress_bars = bars


@contextlib.contextmanager
def ray_session(address: str | None) -> Iterator[Any]:
    """Ray, initialised as RayEngine.address says (see the module docstring); a local
    instance started here is stopped on leaving. Enter it in the main thread when it may start
    one: Ray's processes die with the thread that started them."""
    try:
        import ray
        import ray.data  # noqa: F401 - Ray Data is the `ray[data]` part of the extra
    except ImportError:
        raise RayEngineError(f"the Ray engine needs Ray Data: {RAY_INSTALL}") from None
    if ray.is_initialized():
        yield ray
        return
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address is None:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # else Ray writes ~/.ray/auth_token
        ray.init(num_cpus=available_cpus(), include_dashboard=False,
                 _node_ip_address="127.0.0.1")  # fmt: skip
    else:
        _check_reachable(address)
        try:
            ray.init(address=address)
        except ConnectionError as error:
            raise RayEngineError(f"cannot join the Ray cluster at {address}: {error}") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def _check_reachable(address: str) -> None:
    """A TCP connection to HOST:PORT within CONNECT_TIMEOUT_S ("auto" is Ray's to find):
    ray.init itself would wait minutes for an address nothing answers at."""
    if address == "auto":
        return
    try:
        socket.create_connection(check_address(address), CONNECT_TIMEOUT_S).close()
    except OSError as error:
        raise RayEngineError(
            f"cannot reach the Ray cluster at {address}: {error} (is its head node running, "
            "and the port open to this machine?)"
        ) from None


def check_address(address: str) -> tuple[str, int] | None:
    """HOST and PORT of a "HOST:PORT" address, None for "auto"; RayEngineError for anything
    else, and for Ray Client's ray://, which Ray Data cannot use."""
    if address == "auto":
        return None
    if address.startswith("ray://"):
        raise RayEngineError(
            f"Ray address {address}: Ray Data does not run through Ray Client (ray://). Run "
            "the command on the cluster instead: `ray job submit --address http://HEAD:8265 -- "
            "detmatch label ... --engine ray`, or on one of its nodes with --address auto or "
            "--address HEAD:6379 (docs/scale.md)"
        )
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RayEngineError(f"Ray address {address!r}: expected auto or HOST:PORT")
    return host.strip("[]"), int(port)
