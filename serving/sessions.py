"""onnxruntime sessions as the labeler runs them, and as the exporter checks them.

The choices (measured in BENCHMARKS.md, "ONNX export and labeler"):
- CPU execution provider only: the service targets CPU replicas; a GPU build would add its
  provider in front.
- Graph optimisation ORT_ENABLE_ALL: constant folding, Conv/BN/activation fusions and, on
  x86, the NCHWc layout transform for convolutions; it changes no result beyond float
  rounding (the exporter's parity check runs with these very options).
- intra-op threads = the CPUs this process may use: its CPU set (sched_getaffinity: taskset,
  a container's cpuset) and its cgroup's CPU quota (a container's `--cpus`, a Kubernetes CPU
  limit), whichever is smaller; `detmatch serve --threads` overrides it. Inter-op threads 1
  and sequential execution: both graphs are chains of ops, so parallelism lives inside ops.
- No memory arena: onnxruntime's CPU arena keeps the largest buffers any input ever needed
  (one 8192 x 8192 image left the server 1.2 GB larger for good); without it the memory of
  a run is returned when the run ends. Its cost on normal frames is in BENCHMARKS.md.
- No spinning: between ORT runs the labeler does numpy work (pillarization, projection,
  matching) that busy-waiting pool threads would slow down; replicas on one machine would
  also burn each other's cores.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import onnxruntime as ort

GRAPH_OPTIMIZATION = {
    "disabled": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
    "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
}


CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")


def cgroup_cpu_limit(proc_cgroup: Path = PROC_CGROUP, root: Path = CGROUP_ROOT) -> float | None:
    """The CPU quota of this process's cgroup and its ancestors in CPUs (quota / period, the
    smallest on the way to the root), or None without one. cgroup v2 (`cpu.max`) and v1
    (`cpu.cfs_quota_us` / `cpu.cfs_period_us`)."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    limits = []
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if controllers == "":
            limits += _quotas(root, path, _v2_quota)
        elif "cpu" in controllers.split(","):
            for mount in (controllers, "cpu", "cpu,cpuacct"):
                if (root / mount).is_dir():
                    limits += _quotas(root / mount, path, _v1_quota)
                    break
    return min(limits) if limits else None


def _quotas(mount: Path, path: str, read) -> list[float]:
    """Quotas of the cgroup at mount/path and of each ancestor below mount."""
    found = []
    directory = mount / path.strip("/")
    while True:
        quota = read(directory)
        if quota is not None:
            found.append(quota)
        if directory == mount or mount not in directory.parents:
            return found
        directory = directory.parent


def _v2_quota(directory: Path) -> float | None:
    try:
        quota, period = (directory / "cpu.max").read_text().split()
    except (OSError, ValueError):
        return None
    return None if quota == "max" else int(quota) / int(period)


def _v1_quota(directory: Path) -> float | None:
    try:
        quota = int((directory / "cpu.cfs_quota_us").read_text())
        period = int((directory / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return None if quota <= 0 or period <= 0 else quota / period


def available_cpus() -> int:
    """CPUs this process may use: its CPU set, capped by its cgroup's CPU quota (rounded up,
    as Go and the JVM do)."""
    try:
        cpus = max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # pragma: no cover - not Linux
        cpus = max(os.cpu_count() or 1, 1)
    quota = cgroup_cpu_limit()
    return cpus if quota is None else max(1, min(cpus, math.ceil(quota)))


@dataclass(frozen=True)
class SessionSettings:
    """How onnxruntime runs a model. intra_op_threads 0 means available_cpus()."""

    intra_op_threads: int = 0
    graph_optimization: str = "all"
    allow_spinning: bool = False
    memory_arena: bool = False

    def __post_init__(self) -> None:
        if self.intra_op_threads < 0:
            raise ValueError(f"intra_op_threads must be >= 0, got {self.intra_op_threads}")
        if self.graph_optimization not in GRAPH_OPTIMIZATION:
            raise ValueError(
                f"graph_optimization must be one of {sorted(GRAPH_OPTIMIZATION)}, "
                f"got {self.graph_optimization!r}"
            )

    @property
    def threads(self) -> int:
        return self.intra_op_threads or available_cpus()


def session_options(settings: SessionSettings) -> ort.SessionOptions:
    options = ort.SessionOptions()
    options.graph_optimization_level = GRAPH_OPTIMIZATION[settings.graph_optimization]
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = settings.threads
    options.inter_op_num_threads = 1
    options.enable_cpu_mem_arena = settings.memory_arena
    options.add_session_config_entry(
        "session.intra_op.allow_spinning", "1" if settings.allow_spinning else "0"
    )
    options.log_severity_level = 3  # errors only
    return options


def make_session(
    path: str | os.PathLike, settings: SessionSettings | None = None
) -> ort.InferenceSession:
    """An onnxruntime CPU session for one model file."""
    return ort.InferenceSession(
        str(Path(path)),
        sess_options=session_options(settings or SessionSettings()),
        providers=["CPUExecutionProvider"],
    )
