"""One retraining round, resumable after a kill (`detmatch retrain`).

Stages, journaled in WORK/current/state.json (written atomically after each):
  prepared   the round's inputs are fixed: its parent (the version served when it began) and
             that version's verified training checkpoint, the config, and its frames, gathered
             into WORK/current/data (`retrain.data`) with the store's snapshot id;
  trained    teacher-student training of [retrain] steps whose students and EMA teachers start
             from the parent's models, in WORK/current/run (every process of a torchrun job);
  evaluated  candidate and parent scored on the same gate split (`retrain.gate`), and the
             decision (`serving.manifest.gate_passes`);
  published  the candidate exported as a new version whose manifest records the round (its id,
             parent, both models' figures, the decision and the data); an export is found again
             by the round id, so a round never publishes twice;
  done       promoted if it passed and its parent is still the served version; the report is
             written, the round's frames and checkpoints are deleted and WORK/current becomes
             WORK/rounds/<round id>.
Rank 0 alone gathers, evaluates, exports, promotes and reports. A killed round run again while
its parent is still served and with the same config resumes at its last stage (training from
its last checkpoint, with the frames it gathered); otherwise an unpublished round starts over,
and a published one is finished. A version appears only by the exporter's atomic rename, and is
promoted only after its manifest records a passed gate.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import torch.distributed as dist

from detmatch.checkpoints import list_checkpoints
from detmatch.config import (
    ConfigError,
    ExperimentConfig,
    apply_overrides,
    config_from_dict,
    config_to_dict,
    load_config,
    parse_override,
    refuse_pretraining_overrides,
    teacher_student_config,
)
from detmatch.files import write_json
from detmatch.records import RecordError, from_plain, to_plain
from detmatch.training.distributed import DistributedContext
from retrain.data import GATE_SPLIT, LABELED_SPLIT, UNLABELED_SPLIT, SourceSplits
from serving.manifest import GateFigures, Manifest, RetrainingRecord, RoundData, gate_passes
from serving.repository import (
    RepositoryError,
    list_versions,
    load_manifest,
    promote,
    served_version,
    training_checkpoint,
    version_dir,
)
from serving.store_index import SharedStore

CURRENT = "current"
ROUNDS = "rounds"
STATE_FILE = "state.json"
STAGES = ("prepared", "trained", "evaluated", "published", "done")
PREPARED, TRAINED, EVALUATED, PUBLISHED, DONE = STAGES

T = TypeVar("T")


@dataclass(frozen=True)
class RoundRequest:
    """What `detmatch retrain` was asked: the label store, the original data set (its labeled
    frames, unlabeled pool and gate split), the model repository, the working directory
    (default REPOSITORY/.retrain), a config (None: the served version's) with `--set`
    overrides, and whether to train even when the store holds nothing new."""

    store: Path | SharedStore
    data: Path
    repository: Path
    work: Path
    config: str | None = None
    overrides: tuple[str, ...] = ()
    force: bool = False
    progress: bool = True


@dataclass(frozen=True)
class RoundOutcome:
    """status: "skipped", "promoted" or "not promoted"."""

    status: str
    message: str
    round_id: str | None = None
    version: str | None = None
    report: Path | None = None


@dataclass
class RoundState:
    """The journal of a round in progress (see the module docstring)."""

    round_id: str
    started_at: str
    stage: str
    parent_version: str
    parent_checkpoint: str
    request_config: dict[str, Any]
    config: dict[str, Any]
    data: RoundData
    candidate: GateFigures | None = None
    parent: GateFigures | None = None
    passed: bool | None = None
    version: str | None = None
    promoted: bool | None = None
    outcome: str | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def save(self, directory: Path) -> None:
        write_json(directory / STATE_FILE, to_plain(self))

    @staticmethod
    def load(directory: Path) -> RoundState | None:
        """The journal in directory, None if there is none (a round killed while gathering)."""
        path = directory / STATE_FILE
        if not path.is_file():
            return None
        try:
            state = from_plain(RoundState, json.loads(path.read_text()), "")
        except (ValueError, RecordError) as error:
            raise ValueError(f"{path}: {error}") from None
        if state.stage not in STAGES:
            raise ValueError(f"{path}: unknown stage {state.stage!r}")
        return state

    def record(self) -> RetrainingRecord:
        """The manifest's record of this round (once evaluated)."""
        config = config_from_dict(self.config)
        return RetrainingRecord(
            round_id=self.round_id,
            parent_version=self.parent_version,
            started_at=self.started_at,
            method=config.ssl.method,
            steps=config.train.steps,
            max_map_drop=config.retrain.max_map_drop,
            candidate=self.candidate,
            parent=self.parent,
            passed=bool(self.passed),
            data=self.data,
            config=self.request_config,
        )

    def summary(self) -> dict[str, Any]:
        """What the round report shows (report.json holds all of it)."""
        config = config_from_dict(self.config)
        return {
            "round_id": self.round_id,
            "started_at": self.started_at,
            "parent_version": self.parent_version,
            "parent_checkpoint": self.parent_checkpoint,
            "version": self.version,
            "passed": self.passed,
            "promoted": self.promoted,
            "outcome": self.outcome,
            "method": config.ssl.method,
            "steps": config.train.steps,
            "max_map_drop": config.retrain.max_map_drop,
            "candidate_figures": to_plain(self.candidate),
            "parent_figures": to_plain(self.parent),
            "data": to_plain(self.data),
            "timings": self.timings,
            "config": self.request_config,
        }


def log_stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run_round(
    request: RoundRequest,
    context: DistributedContext,
    log: Callable[[str], None] = log_stderr,
) -> RoundOutcome:
    """One round (see the module docstring), or its resumption; on every process of a torchrun
    job, all of which get the outcome. The caller holds the repository's retraining lock."""
    plan = main_only(context, lambda: _plan(request, log))
    if isinstance(plan, RoundOutcome):
        return plan
    state = plan
    if STAGES.index(state.stage) < STAGES.index(TRAINED):
        started = time.monotonic()
        _train(state, request, context)
        if context.is_main:
            _advance(state, request, TRAINED, "train", started)
    return main_only(context, lambda: _finish(state, request, context, log))


def main_only(context: DistributedContext, work: Callable[[], T]) -> T:
    """work() on rank 0; its result, or its failure, on every rank."""
    if not context.enabled:
        return work()
    payload: list[Any] = [None]
    failure: BaseException | None = None
    if context.is_main:
        try:
            payload = [("ok", work())]
        except Exception as error:  # noqa: BLE001 - re-raised below, after the other ranks know
            failure = error
            payload = [("failed", f"{type(error).__name__}: {error}")]
    dist.broadcast_object_list(payload, src=0)
    kind, value = payload[0]
    if failure is not None:
        raise failure
    if kind == "failed":
        raise RuntimeError(f"the retraining round failed on rank 0: {value}")
    return value


# --- rank 0: planning and gathering ---------------------------------------------------------------


def resolve_config(
    parent: Manifest, config: str | None, overrides: tuple[str, ...]
) -> ExperimentConfig:
    """The config a round trains with: the parent version's (or `config`), `--set` overrides,
    and DetMatch when its method is labeled-only. It must describe the parent's detectors. A
    parent a round made gives the config that round was asked for (its own run's config names
    the round's internal splits)."""
    record = parent.retraining
    parent_config = config_from_dict(record.config if record else parent.training.config)
    resolved = apply_overrides(load_config(config) if config else parent_config, overrides)
    if resolved.ssl.method == "labeled-only":
        resolved = resolved.replace("ssl", method="detmatch")
    refuse_pretraining_overrides(resolved, overrides)
    for text in overrides:
        if parse_override(text)[:2] == ("ssl", "steps"):
            raise ConfigError(f"--set {text!r}: a round's length is [retrain] steps")
    ours, theirs = config_to_dict(resolved), config_to_dict(parent_config)
    for section in ("detector2d", "detector3d"):
        for key, value in ours[section].items():
            if theirs[section].get(key) != value:
                raise ValueError(
                    f"the round's [{section}] {key} is {value!r}, but version {parent.version} "
                    f"was trained with {theirs[section].get(key)!r}: a round continues the "
                    "served models, so its config must describe the same detectors"
                )
    if resolved.data.classes != parent_config.data.classes:
        raise ValueError(
            f"the round's [data] classes {list(resolved.data.classes)} differ from version "
            f"{parent.version}'s {list(parent_config.data.classes)}"
        )
    return resolved


def last_round(repository: Path) -> RetrainingRecord | None:
    """The record of the newest version a round made (None if no round published one)."""
    for version in reversed(list_versions(repository)):
        try:
            manifest = load_manifest(repository / version)
        except RepositoryError:
            continue
        if manifest.retraining is not None:
            return manifest.retraining
    return None


def published_version(repository: Path, round_id: str) -> str | None:
    """The version a round published, if it did."""
    for version in reversed(list_versions(repository)):
        try:
            manifest = load_manifest(repository / version)
        except RepositoryError:
            continue
        if manifest.retraining is not None and manifest.retraining.round_id == round_id:
            return version
    return None


def _plan(request: RoundRequest, log: Callable[[str], None]) -> RoundState | RoundOutcome:
    from retrain.snapshot import store_snapshot

    repository = request.repository
    served = served_version(repository)
    if served is None:
        raise FileNotFoundError(
            f"model repository {repository} has no promoted version: a round continues the "
            f"served model; publish and promote one first (detmatch-export --checkpoint RUN "
            f"--repository {repository} --promote)"
        )
    parent_dir = version_dir(repository, served)
    parent = load_manifest(parent_dir)
    config = resolve_config(parent, request.config, request.overrides)
    current = request.work / CURRENT
    state = RoundState.load(current) if current.is_dir() else None
    if state is not None and state.stage == EVALUATED:
        published = published_version(repository, state.round_id)
        if published is not None:  # killed between the export's rename and the journal
            state.version, state.stage = published, PUBLISHED
            state.save(current)
    if state is not None:
        if STAGES.index(state.stage) >= STAGES.index(PUBLISHED):
            log(f"round {state.round_id}: finishing it (it published version {state.version})")
            return state
        if state.parent_version == served and state.request_config == config_to_dict(config):
            log(f"round {state.round_id}: resuming after stage {state.stage!r}")
            return state
        why = (
            f"version {served} is served now, not {state.parent_version}"
            if state.parent_version != served
            else "the config differs"
        )
        log(f"round {state.round_id}: discarding the unfinished round ({why}); starting over")
    if current.exists():
        shutil.rmtree(current)
    snapshot = store_snapshot(request.store)
    if not request.force:
        previous = last_round(repository)
        if snapshot.frames == 0:
            return RoundOutcome("skipped", f"skipped: the label store {request.store} is empty")
        if previous is not None and previous.data.store_snapshot == snapshot.id:
            return RoundOutcome(
                "skipped",
                f"skipped: no new frames since round {previous.round_id} (the label store's "
                f"{snapshot.frames} frames are those it read; snapshot {snapshot.id[:12]})",
            )
    parent_checkpoint = training_checkpoint(parent_dir, parent)
    started = time.monotonic()
    round_id = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + secrets.token_hex(3)
    log(f"round {round_id}: continuing version {served}; gathering frames into {current}")
    from retrain.data import compose_round_data

    data = compose_round_data(
        request.data,
        request.store,
        current / "data",
        SourceSplits(config.data.train_split, config.ssl.unlabeled_split, config.data.val_split),
        config.retrain.stored_labels,
        progress=request.progress,
        reviewed_gate_fraction=config.retrain.reviewed_gate_fraction,
    )
    pool = data.unlabeled + (data.stored if data.stored_labels == "pool" else 0)
    if pool == 0:
        raise ValueError(
            f"round {round_id} has no unlabeled frames: the unlabeled split "
            f"{config.ssl.unlabeled_split!r} of {request.data} is empty and no stored frame "
            "joined the pool"
        )
    log(
        f"round {round_id}: {data.labeled} labeled, {data.reviewed} human-reviewed "
        f"({data.reviewed_gate} of them in the gate), {data.stored} machine-labeled and "
        f"{data.unlabeled} unlabeled frames ({data.excluded} stored frames left out as gate "
        f"frames); gate {data.gate} frames"
    )
    state = RoundState(
        round_id=round_id,
        started_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        stage=PREPARED,
        parent_version=served,
        parent_checkpoint=str(parent_checkpoint),
        request_config=config_to_dict(config),
        config=config_to_dict(_training_config(config, current / "data", parent_checkpoint)),
        data=data,
        timings={"prepare": round(time.monotonic() - started, 3)},
    )
    state.save(current)
    return state


def _training_config(config: ExperimentConfig, data_dir: Path, parent: Path) -> ExperimentConfig:
    """The round's teacher-student run: its frames, [retrain] steps from the parent's models
    at the [ssl] stage's rates, evaluated once, at the end."""
    steps = config.retrain.steps
    config = config.replace(
        "data", root=str(data_dir), train_split=LABELED_SPLIT, val_split=GATE_SPLIT
    )
    config = config.replace(
        "ssl", unlabeled_split=UNLABELED_SPLIT, pretrained=str(parent), steps=steps
    )
    return teacher_student_config(config).replace(
        "train", eval_every=steps, checkpoint_every=min(config.train.checkpoint_every, steps)
    )


# --- every rank: training -------------------------------------------------------------------------


def _train(state: RoundState, request: RoundRequest, context: DistributedContext) -> None:
    from detmatch.training.semi_supervised import trainer_type

    config = config_from_dict(state.config)
    run_dir = request.work / CURRENT / "run"
    found = list_checkpoints(run_dir)
    if found and found[-1].name == f"step_{config.train.steps:08d}.pt":
        return
    trainer = trainer_type(config.ssl.method)(config, run_dir, context)
    if trainer.resume() and context.is_main:
        log_stderr(f"round {state.round_id}: training resumes at step {trainer.state.step}")
    trainer.run()


# --- rank 0: gate, export, promotion, report ------------------------------------------------------


def _advance(state: RoundState, request: RoundRequest, stage: str, timing: str, since: float):
    state.stage = stage
    state.timings[timing] = round(state.timings.get(timing, 0.0) + time.monotonic() - since, 3)
    state.save(request.work / CURRENT)


def _finish(
    state: RoundState,
    request: RoundRequest,
    context: DistributedContext,
    log: Callable[[str], None],
) -> RoundOutcome:
    from export.onnx_export import export_checkpoint
    from retrain.gate import gate_figures

    current, repository = request.work / CURRENT, request.repository
    if state.stage == TRAINED:
        started = time.monotonic()
        log(
            f"round {state.round_id}: scoring the candidate and version {state.parent_version} "
            f"on the gate ({state.data.gate} frames)"
        )
        parent = training_checkpoint(version_dir(repository, state.parent_version))
        state.candidate = gate_figures(
            current / "run", current / "data", GATE_SPLIT, context.device
        )
        state.parent = gate_figures(parent, current / "data", GATE_SPLIT, context.device)
        config = config_from_dict(state.config)
        state.passed = gate_passes(state.candidate, state.parent, config.retrain.max_map_drop)
        _advance(state, request, EVALUATED, "evaluate", started)
    if state.stage == EVALUATED:
        started = time.monotonic()
        version = published_version(repository, state.round_id)
        if version is None:
            log(f"round {state.round_id}: exporting the candidate")
            version = export_checkpoint(
                current / "run", repository, retraining=state.record(), log=log
            ).version
        state.version = version
        _advance(state, request, PUBLISHED, "export", started)
    if state.stage == PUBLISHED:
        state.promoted, state.outcome = _promote(repository, state)
        log(f"round {state.round_id}: {state.outcome}")
        state.stage = DONE
        state.save(current)
    return _complete(state, request)


def _promote(repository: Path, state: RoundState) -> tuple[bool, str]:
    """Promote a passed candidate while its parent is still served; (promoted, outcome)."""
    served = served_version(repository)
    figures = (
        f"2D mAP {state.candidate.map('2d'):.1f} vs {state.parent.map('2d'):.1f}, "
        f"3D mAP {state.candidate.map('3d'):.1f} vs {state.parent.map('3d'):.1f}"
    )
    version, parent = state.version, state.parent_version
    if not state.passed:
        return False, f"version {version} not promoted: it failed the gate ({figures})"
    if served == version:
        return True, f"version {version} promoted ({figures})"
    if served != parent:
        return False, (
            f"version {version} passed the gate ({figures}) but was not promoted: the served "
            f"version changed from {parent} to {served} during the round"
        )
    promote(repository, version)
    return True, f"version {version} promoted ({figures})"


def _complete(state: RoundState, request: RoundRequest) -> RoundOutcome:
    """Report, delete the round's frames and checkpoints, move it to WORK/rounds/<id>."""
    from retrain.report import write_round_report

    current = request.work / CURRENT
    write_round_report(current, state.summary())
    shutil.rmtree(current / "data", ignore_errors=True)
    shutil.rmtree(current / "run" / "checkpoints", ignore_errors=True)
    final = request.work / ROUNDS / state.round_id
    final.parent.mkdir(parents=True, exist_ok=True)
    os.replace(current, final)
    status = "promoted" if state.promoted else "not promoted"
    return RoundOutcome(status, state.outcome, state.round_id, state.version, final / "report.md")
