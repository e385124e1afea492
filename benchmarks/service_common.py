"""What the service benchmarks share: a model repository, `detmatch serve` in a process of its
own (torch blocked, as in production), the KITTI sample frames as requests, and readings of
the server's memory. Run the benchmarks from the repository root as modules:

    python -m benchmarks.service_load ...

The model: a config's two detectors with random weights (torch.manual_seed(0)), exported by
`export_checkpoint` (parity check included). Latency and robustness do not depend on the
weights; `configs/synth_cpu.toml` is the CPU benchmark model, `configs/tiny.toml` a fast one.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from serving.health_check import wait_until_serving

REPO = Path(__file__).resolve().parents[1]
KITTI_SAMPLE = REPO / "tests" / "data" / "kitti"
SAMPLE_IDS = ("000000", "000001", "000002")
TORCH_FREE_SERVE = (
    "import sys; sys.modules['torch'] = None; "
    "from commands.main import main; sys.exit(main(['serve'] + sys.argv[1:]))"
)


def prepare_repository(
    work: Path, config: str = "configs/tiny.toml", checkpoint: str | None = None
) -> Path:
    """A model repository whose version 000001 (promoted) is `config` with random weights, or
    the trained `checkpoint` (its own config); made once per work directory."""
    if checkpoint:
        digest = hashlib.sha1(str(Path(checkpoint).resolve()).encode()).hexdigest()
        name = f"checkpoint_{digest[:10]}"
    else:
        name = Path(config).stem
    repository = work / f"repository_{name}"
    if (repository / "000001" / "PROMOTED").is_file():
        return repository
    work.mkdir(parents=True, exist_ok=True)  # --work may name a folder not made yet
    import torch

    from export.onnx_export import export_checkpoint

    if checkpoint is None:
        checkpoint = work / f"{name}.pt"
        _random_checkpoint(config, checkpoint)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        export_checkpoint(checkpoint, repository, promote_version=True, synthetic_frames=1)
    finally:
        torch.set_num_threads(threads)
    return repository


def _random_checkpoint(config: str, path: Path) -> None:
    import torch

    from detmatch.config import config_to_dict, load_config
    from detmatch.models.detector2d import CenterNet2D
    from detmatch.models.detector3d import PointPillars3D

    loaded = load_config(REPO / config)
    torch.manual_seed(0)
    classes = len(loaded.data.classes)
    torch.save(
        {
            "format": 1,
            "step": 0,
            "config": config_to_dict(loaded),
            "model_2d": CenterNet2D(loaded.detector2d, classes).state_dict(),
            "model_3d": PointPillars3D(loaded.detector3d, classes).state_dict(),
            "metrics": {},
        },
        path,
    )


@dataclass
class ServerProcess:
    process: subprocess.Popen
    target: str
    log_path: Path
    lines: list[str] = field(default_factory=list)

    @property
    def pid(self) -> int:
        return self.process.pid

    def rss_mib(self) -> float:
        return rss_mib(self.process.pid)

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""


@contextlib.contextmanager
def serve(
    repository: Path, store: Path, *args: str, env: dict[str, str] | None = None, port: int = 0
) -> Iterator[ServerProcess]:
    """`detmatch serve` in a subprocess that cannot import torch (with --no-auth unless env
    holds DETMATCH_TOKEN); its log goes to a file beside the store. Waits until SERVING
    (plaintext servers) or until it listens (TLS)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO), **(env or {})}
    if "--no-auth" not in args and not env.get("DETMATCH_TOKEN"):
        args = ("--no-auth", *args)
    store.parent.mkdir(parents=True, exist_ok=True)
    log_path = store.parent / f"{store.name}.server.log"
    command = [sys.executable, "-c", TORCH_FREE_SERVE, "--repository", str(repository),
               "--store", str(store), "--port", str(port), "--shard", "s0", *args]  # fmt: skip
    with open(log_path, "a") as log:
        process = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE,
                                   stderr=log, text=True)  # fmt: skip
    try:
        line = process.stdout.readline()
        if not line.startswith("listening on "):
            process.kill()
            raise RuntimeError(f"server did not start: {line!r}\n{log_path.read_text()[-3000:]}")
        target = line.split()[-1]
        if "--tls-cert" not in args:
            status = wait_until_serving(target, wait_s=120, poll_s=0.05)
            if status != "SERVING":
                raise TimeoutError(f"{target} is {status}, not SERVING, after 120 s")
        yield ServerProcess(process, target, log_path)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)  # drains, and the store logs its counts
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
        process.wait(timeout=60)
        process.stdout.close()


def int8_repository(work: Path, repository: Path) -> Path:
    """A copy of repository whose promoted version is an INT8 version of its 000001
    (`detmatch-export --quantize int8`, calibrated on two KITTI sample frames, parity on the
    third and not enforced: the graphs' speed is what the service benchmarks need of it)."""
    from export.quantize import quantize_version

    target = work / f"{repository.name}_int8"
    if not (target / "000002" / "PROMOTED").is_file():
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(repository, target)
        quantize_version(target, "000001", KITTI_SAMPLE, calibration_frames=2, parity_frames=1,
                         min_agreement=0.0, promote_version=True)  # fmt: skip
    return target


def sample_requests(store: bool = True, prefix: str = "", raw_image: bool = False) -> list:
    """One LabelFrameRequest per KITTI sample frame (frame ids prefix + the KITTI id); raw_image:
    the pixels uncompressed instead of the PNG files."""
    from serving.client import kitti_frame
    from serving.messages import request_message
    from serving.request import LabelOptions

    options = LabelOptions(store=store)
    return [
        request_message(
            kitti_frame(
                KITTI_SAMPLE, i, send_as=f"{prefix}{i}", options=options, raw_image=raw_image
            )
        )  # fmt: skip
        for i in SAMPLE_IDS
    ]


def rss_mib(pid: int) -> float:
    """A process's resident set now (VmRSS), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time a process has used (its threads included), seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class RssSampler:
    """Samples a process's RSS every period_s on a thread: (seconds since start, MiB)."""

    def __init__(self, pid: int, period_s: float = 0.5) -> None:
        self.pid, self.period_s = pid, period_s
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        start = time.monotonic()
        while not self._stop.is_set():
            with contextlib.suppress(OSError):
                self.samples.append((time.monotonic() - start, rss_mib(self.pid)))
            self._stop.wait(self.period_s)

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def peak(self) -> float:
        return max((m for _, m in self.samples), default=float("nan"))


def percentiles(seconds: list[float]) -> dict[str, float]:
    """p50 / p95 / p99 / max in milliseconds."""
    if not seconds:
        return {"p50_ms": float("nan"), "p95_ms": float("nan"), "p99_ms": float("nan"),
                "max_ms": float("nan")}  # fmt: skip
    values = np.asarray(seconds) * 1000
    return {
        "p50_ms": float(np.percentile(values, 50)),
        "p95_ms": float(np.percentile(values, 95)),
        "p99_ms": float(np.percentile(values, 99)),
        "max_ms": float(values.max()),
    }
