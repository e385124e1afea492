"""`detmatch demo`: the whole product on a fresh machine, with nothing but the package.

 1. a synthetic paired camera + LiDAR data set (train / val, a labeled fraction of train), and
    a second, unseen set of frames to send to the service;
 2. labeled-only pre-training of both detectors;
 3. DetMatch from the pre-trained weights (labeled + unlabeled frames);
 4. both runs scored on val (moderate R40 AP): did DetMatch beat labeled-only at this size?
 5. the DetMatch models exported to ONNX (parity-checked) as version 000001, promoted;
 6. `detmatch serve` started as a real process on a free port;
 7. the unseen frames labeled through real gRPC calls, into the label store;
 8. one retraining round from the stored labels (`retrain.round`), promoted if it passes;
 9. the running server picking the new version up by itself;
10. a report directory: report.md with the tables, pictures of served labels (image and
    bird's-eye view), training curves, the round's per-class AP and a Figure-3 plot.

Sizes (`SIZES`) trade minutes for figures: "ci" and "small" (the default) run on a 2-core CPU,
"medium" and "large" want more cores or a GPU.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from detmatch.config import ExperimentConfig, load_config, teacher_student_config
from retrain.demo_report import verdict, write_demo_report
from retrain.demo_results import DEFAULT_OUT, DEFAULT_SIZE, SIZES, DemoResults

if TYPE_CHECKING:  # no torch at import: training is imported by the stages that train
    from detmatch.training.distributed import DistributedContext


class Stages:
    """Numbered stage headings on stderr and each stage's wall time."""

    def __init__(self, results: DemoResults, total: int) -> None:
        self.results = results
        self.total = total
        self.count = 0

    @contextlib.contextmanager
    def __call__(self, key: str, title: str) -> Iterator[None]:
        self.count += 1
        print(f"\n[{self.count}/{self.total}] {title}", file=sys.stderr, flush=True)
        started = time.monotonic()
        yield
        self.results.timings[key] = round(time.monotonic() - started, 1)


def run_demo(
    out: str | os.PathLike = DEFAULT_OUT,
    size: str = DEFAULT_SIZE,
    seed: int = 0,
    workers: int = 1,
    device: str = "auto",
) -> Path:
    """Run every stage (see the module docstring) into out, which must be new or empty;
    returns the report's path."""
    from detmatch.training.distributed import init_distributed

    if size not in SIZES:
        raise ValueError(f"--size must be one of {', '.join(SIZES)}, got {size!r}")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(
            f"{out} already exists and is not empty: pass --out NEW_DIR or remove it"
        )
    started = time.monotonic()
    results = DemoResults(SIZES[size], out, seed)
    context = init_distributed(device)
    results.device = str(context.device)
    stage = Stages(results, total=10)
    with stage("data", "synthetic data"):
        config = _make_data(results, workers)
    with stage("pretrain", "labeled-only pre-training"):
        results.labeled_only = _train(config, out / "runs" / "pretrain", context)
    with stage("detmatch", "DetMatch from the pre-trained weights"):
        steps = results.size.detmatch_steps
        detmatch_config = teacher_student_config(
            config.replace(
                "ssl", method="detmatch", pretrained=str(out / "runs" / "pretrain"), steps=steps
            )
        ).replace("train", eval_every=steps)
        results.detmatch = _train(detmatch_config, out / "runs" / "detmatch", context)
    with stage("compare", "labeled-only vs DetMatch on val"):
        print(verdict(results), file=sys.stderr)
    with stage("export", "export DetMatch to ONNX as version 000001, promoted"):
        from export.onnx_export import export_checkpoint

        export_checkpoint(
            out / "runs" / "detmatch",
            out / "models",
            promote_version=True,
            log=lambda message: print(message, file=sys.stderr),
        )
    with _server(out, stage) as service:
        with stage("label", "label unseen frames through gRPC into the label store"):
            _label_through_service(results, service)
        with stage("retrain", "a retraining round from the stored labels"):
            _retrain(results, context)
        with stage("swap", "the running server picks up the promoted version"):
            _wait_for_swap(results, service)
    with stage("report", "report"):
        results.timings["total"] = round(time.monotonic() - started, 1)
        report = write_demo_report(results)
    return report


def _make_data(results: DemoResults, workers: int) -> ExperimentConfig:
    """The synthetic set with its labeled split, the unseen frames; the training config."""
    from detmatch.data.kitti import read_image_set
    from detmatch.data.splits import make_split
    from detmatch.data.synth import generate_dataset

    size, out = results.size, results.out
    data = out / "data"
    generate_dataset(data, size.frames, results.seed, size.resolution, workers, size.val_fraction)
    split = make_split(data, size.labeled_fraction, results.seed)
    generate_dataset(
        out / "new_frames",
        size.new_frames,
        results.seed + 1,
        size.resolution,
        workers,
        val_fraction=0.25,
    )
    results.splits = {
        "labeled": split.labeled_path.stem,
        "unlabeled": split.unlabeled_path.stem,
        "num_labeled": split.num_labeled,
        "num_unlabeled": split.num_unlabeled,
        "num_val": len(read_image_set(data / "ImageSets" / "val.txt")),
        "num_new": size.new_frames,
    }
    config = load_config(size.config)
    config = config.replace(
        "data", root=str(data), train_split=split.labeled_path.stem, val_split="val"
    )
    config = config.replace("ssl", unlabeled_split=split.unlabeled_path.stem)
    steps = size.pretrain_steps
    return config.replace("train", steps=steps, eval_every=steps)


def _train(config: ExperimentConfig, run_dir: Path, context: DistributedContext) -> dict:
    """Train a run; its final evaluation on val (moderate R40 AP per class, 2d/3d/bev)."""
    from detmatch.training.semi_supervised import trainer_type

    state = trainer_type(config.ssl.method)(config, run_dir, context).run()
    return {k: v for k, v in state.metrics.items() if k in ("2d", "3d", "bev")}


@dataclass(frozen=True)
class Service:
    """A running `detmatch serve`: its address and the bearer token its clients send."""

    target: str
    token: str


@contextlib.contextmanager
def _server(out: Path, stage: Stages) -> Iterator[Service]:
    """`detmatch serve` as a process on a free port, with a fresh bearer token (authentication
    is never off); yields its target and token once it is SERVING."""
    from serving.health_check import wait_until_serving

    with stage("serve", "start `detmatch serve` (a real gRPC server process)"):
        logs = out / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        command = [sys.executable, "-m", "commands.main", "serve", "--repository",
                   str(out / "models"), "--store", str(out / "store"), "--port", "0",
                   "--shard", "demo", "--poll-s", "0.5", "--grace-s", "5"]  # fmt: skip
        stderr = (logs / "serve.log").open("w")
        token = secrets.token_urlsafe(24)
        environment = {**os.environ, "DETMATCH_TOKEN": token}
        process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=stderr, text=True, env=environment
        )
    try:
        line = process.stdout.readline()
        if not line.startswith("listening on "):
            raise RuntimeError(f"detmatch serve did not start (see {logs / 'serve.log'})")
        target = "127.0.0.1:" + line.split()[-1].rsplit(":", 1)[1]
        status = wait_until_serving(target, wait_s=120)
        if status != "SERVING":
            raise RuntimeError(f"detmatch serve at {target} is {status} (see {logs})")
        print(f"serving at {target}; log: {logs / 'serve.log'}", file=sys.stderr)
        yield Service(target, token)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        process.stdout.close()
        stderr.close()


def _label_through_service(results: DemoResults, service: Service) -> None:
    from detmatch.data.kitti import KittiDataset
    from serving.client import LabelingClient

    frames = KittiDataset(results.out / "new_frames").ids()
    latencies, labels, versions = [], 0, set()
    with LabelingClient(service.target, token=service.token) as client:
        for frame_id in tqdm(frames, desc="LabelFrame", unit="frame", dynamic_ncols=True):
            started = time.monotonic()
            response = client.label_kitti_frame(
                results.out / "new_frames", frame_id, send_as=f"new-{frame_id}"
            )
            latencies.append(time.monotonic() - started)
            labels += len(response.labels)
            versions.add(response.model_version)
            if not response.stored:
                raise RuntimeError(f"the service did not store frame new-{frame_id}")
    results.served = {
        "frames": len(frames),
        "labels": labels,
        "versions": sorted(versions),
        "mean_latency_ms": round(1000 * sum(latencies) / max(len(latencies), 1), 1),
        "ids": [f"new-{i}" for i in frames],
    }


def _retrain(results: DemoResults, context: DistributedContext) -> None:
    from retrain.round import RoundRequest
    from retrain.schedule import run_scheduled

    out = results.out
    request = RoundRequest(
        store=out / "store",
        data=out / "data",
        repository=out / "models",
        work=out / "retrain",
        overrides=(f"retrain.steps={results.size.round_steps}",),
    )
    (outcome,) = run_scheduled(request, context)
    results.round = {**asdict(outcome), "report": str(outcome.report)}
    print(outcome.message, file=sys.stderr)


def _wait_for_swap(results: DemoResults, service: Service, timeout_s: float = 120.0) -> None:
    """Ask the running server for its version until it serves the promoted one; label one
    frame with it."""
    from serving.client import LabelingClient

    expected = results.round.get("version") if results.round["status"] == "promoted" else None
    started = time.monotonic()
    with LabelingClient(service.target, token=service.token) as client:
        version = client.model_info().version
        while expected is not None and version != expected:
            if time.monotonic() - started > timeout_s:
                raise RuntimeError(f"the server still serves {version}, not {expected}")
            time.sleep(0.2)
            version = client.model_info().version
        frame = results.served["ids"][0].removeprefix("new-")
        response = client.label_kitti_frame(results.out / "new_frames", frame, store=False)
    results.swap = {
        "expected": expected,
        "served": version,
        "answered_by": response.model_version,
        "seconds": round(time.monotonic() - started, 1),
    }
    print(f"the server answers with version {response.model_version}", file=sys.stderr)
