"""onnxruntime sessions as the labeler runs them, and as the exporter checks them.

The choices (measured in BENCHMARKS.md, "ONNX export and labeler"):
- CPU execution provider only: the service targets CPU replicas; a GPU build would add its
  provider in front.
- Graph optimisation ORT_ENABLE_ALL: constant folding, Conv/BN/activation fusions and, on
  x86, the NCHWc layout transform for convolutions; it changes no result beyond float
  rounding (the exporter's parity check runs with these very options).
- intra-op threads = the CPUs this process may run on (sched_getaffinity, so a container's
  or taskset's CPU set is respected), inter-op threads 1 and sequential execution: both
  graphs are chains of ops, so parallelism lives inside ops.
- No spinning: between ORT runs the labeler does numpy work (pillarization, projection,
  matching) that busy-waiting pool threads would slow down; replicas on one machine would
  also burn each other's cores.
"""

from __future__ import annotations

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


def available_cpus() -> int:
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # pragma: no cover - not Linux
        return max(os.cpu_count() or 1, 1)


@dataclass(frozen=True)
class SessionSettings:
    """How onnxruntime runs a model. intra_op_threads 0 means available_cpus()."""

    intra_op_threads: int = 0
    graph_optimization: str = "all"
    allow_spinning: bool = False

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
