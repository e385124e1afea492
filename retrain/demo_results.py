"""What `detmatch demo` runs and what it found: its sizes and its results record.

The demo (`retrain.demo`) fills a `DemoResults` stage by stage and the report
(`retrain.demo_report`) renders it; both import this module, neither imports the other's
record. No torch and nothing heavy at import: the command line reads `SIZES` for --help.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

DEFAULT_OUT = "detmatch_demo"


@dataclass(frozen=True)
class DemoSize:
    """frames: synthetic frames (val_fraction of them val, labeled_fraction of train labeled);
    new_frames: unseen frames sent to the service; steps of each training stage."""

    name: str
    frames: int
    new_frames: int
    pretrain_steps: int
    detmatch_steps: int
    round_steps: int
    labeled_fraction: float = 0.2
    val_fraction: float = 0.25
    config: str = "demo"
    resolution: str = "half"
    about: str = ""


SIZES = {
    size.name: size
    for size in (
        DemoSize("smoke", 10, 3, 4, 3, 2, labeled_fraction=0.4, val_fraction=0.3,
                 config="tiny", about="under a minute: every stage runs, the figures mean nothing"),
        DemoSize("ci", 48, 8, 200, 60, 30, labeled_fraction=0.3,
                 about="about 3 minutes on 2 CPU cores, CI's main job"),
        DemoSize("small", 160, 24, 500, 150, 80, labeled_fraction=0.25,
                 about="about 10 minutes on 2 CPU cores, the default"),
        DemoSize("medium", 600, 60, 1500, 600, 300, labeled_fraction=0.1,
                 about="about an hour on 8 CPU cores, minutes on a GPU"),
        DemoSize("large", 2000, 200, 3000, 600, 300, config="ssl_cpu", labeled_fraction=0.05,
                 about="the benchmark's set-up, BENCHMARKS.md: a GPU"),
    )
}  # fmt: skip
DEFAULT_SIZE = "small"


@dataclass
class DemoResults:
    """What the report shows; filled in stage by stage."""

    size: DemoSize
    out: Path
    seed: int
    device: str = "cpu"
    timings: dict[str, float] = field(default_factory=dict)
    splits: dict[str, Any] = field(default_factory=dict)
    labeled_only: dict[str, Any] = field(default_factory=dict)
    detmatch: dict[str, Any] = field(default_factory=dict)
    served: dict[str, Any] = field(default_factory=dict)
    round: dict[str, Any] = field(default_factory=dict)
    swap: dict[str, Any] = field(default_factory=dict)


def describe_sizes() -> str:
    return "; ".join(
        f"{s.name}: {s.frames} frames, steps {s.pretrain_steps}/{s.detmatch_steps}/"
        f"{s.round_steps} ({s.about})"
        for s in SIZES.values()
    )


def results_json(results: DemoResults) -> dict[str, Any]:
    plain = asdict(results)
    plain["out"] = str(results.out)
    return json.loads(json.dumps(plain, default=str))
