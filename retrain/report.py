"""A retraining round's report: report.md (the decision, both models' figures, the data),
report.json (the same, and everything the round recorded) and per_class_ap.png (both models'
moderate AP per class, 2D, 3D and BEV)."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

from detmatch.files import atomic_write_bytes
from serving.manifest import GATED_MODALITIES, GateFigures, RoundData

REPORT_MARKDOWN = "report.md"
REPORT_JSON = "report.json"
AP_PLOT = "per_class_ap.png"
MODALITY_NAMES = {"2d": "2D", "3d": "3D", "bev": "BEV"}


def ap_table(parent: GateFigures, candidate: GateFigures, parent_name: str, name: str) -> str:
    """Markdown rows: modality, class, parent AP, candidate AP, change (mAP rows in bold)."""
    lines = [
        f"| modality | class | {parent_name} | {name} | change |",
        "|---|---|---|---|---|",
    ]
    for modality, label in MODALITY_NAMES.items():
        before, after = getattr(parent, f"ap_{modality}"), getattr(candidate, f"ap_{modality}")
        gated = "" if modality in GATED_MODALITIES else " (not gated)"
        for key in [k for k in before if k != "mAP"] + ["mAP"]:
            cell = f"**{key}**{gated}" if key == "mAP" else key
            lines.append(
                f"| {label} | {cell} | {before[key]:.1f} | {after[key]:.1f} | "
                f"{after[key] - before[key]:+.1f} |"
            )
    return "\n".join(lines)


def data_table(data: RoundData) -> str:
    splits = data.splits
    use = "unlabeled pool" if data.stored_labels == "pool" else "labeled (stored labels as targets)"
    return "\n".join(
        [
            "| source | frames |",
            "|---|---|",
            f"| original labeled frames (`{splits['labeled']}`) | {data.labeled} |",
            f"| original unlabeled pool (`{splits['unlabeled']}`) | {data.unlabeled} |",
            f"| human-reviewed stored frames (`detmatch review import`, 3D), labeled "
            f"| {data.reviewed - data.reviewed_gate} |",
            f"| label store, machine-labeled (snapshot `{data.store_snapshot[:12]}`), used as "
            f"{use} | {data.stored} |",
            f"| stored frames left out (identical to gate frames) | {data.excluded} |",
            f"| gate (`{splits['gate']}`, held out; {data.reviewed_gate} human-reviewed) "
            f"| {data.gate} |",
        ]
    )


def per_class_ap_figure(parent: GateFigures, candidate: GateFigures, parent_name: str, name: str):
    """A matplotlib Figure: grouped bars of both models' AP per class and mAP, one panel per
    modality, on one y-axis whose limit leaves room for every bar and its value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    panels = [
        (label, getattr(parent, f"ap_{modality}"), getattr(candidate, f"ap_{modality}"))
        for modality, label in MODALITY_NAMES.items()
    ]
    top = max(1.0, *(v for _, before, after in panels for v in (*before.values(), *after.values())))
    figure, axes = plt.subplots(1, len(panels), figsize=(13, 3.8), dpi=100, sharey=True)
    for axis, (label, before, after) in zip(axes, panels, strict=True):
        keys = [k for k in before if k != "mAP"] + ["mAP"]
        x = np.arange(len(keys))
        for offset, values, bar_name, colour in (
            (-0.2, before, parent_name, "tab:gray"),
            (0.2, after, name, "tab:blue"),
        ):
            bars = axis.bar(
                x + offset, [values[k] for k in keys], 0.4, label=bar_name, color=colour
            )
            axis.bar_label(bars, fmt="%.1f", fontsize=7)
        axis.set_xticks(x, keys)
        axis.set_title(f"{label} moderate AP (R40)")
        axis.grid(axis="y", alpha=0.3)
    axes[0].set_ylim(0, top * 1.15)  # shared: one limit for every panel
    axes[0].set_ylabel("AP (%)")
    figure.legend(*axes[0].get_legend_handles_labels(), loc="upper right", ncols=2, fontsize=8)
    figure.tight_layout(rect=(0, 0, 1, 0.92))
    return figure


def plot_per_class_ap(
    parent: GateFigures, candidate: GateFigures, parent_name: str, name: str
) -> bytes:
    """PNG bytes of `per_class_ap_figure`."""
    return figure_png(per_class_ap_figure(parent, candidate, parent_name, name))


def figure_png(figure) -> bytes:
    """A matplotlib Figure as PNG bytes; the figure is closed."""
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    plt.close(figure)
    return buffer.getvalue()


def write_round_report(directory: Path, summary: dict[str, Any]) -> Path:
    """Write the three files into directory from a round's summary (`RoundState.summary()`);
    returns report.md's path."""
    directory = Path(directory)
    parent = GateFigures(**summary["parent_figures"])
    candidate = GateFigures(**summary["candidate_figures"])
    data = RoundData(**summary["data"])
    parent_name = f"parent {summary['parent_version']}"
    name = f"candidate {summary['version']}" if summary.get("version") else "candidate"
    atomic_write_bytes(directory / AP_PLOT, plot_per_class_ap(parent, candidate, parent_name, name))
    drop = summary["max_map_drop"]
    timings = ", ".join(f"{k} {v:.0f} s" for k, v in summary.get("timings", {}).items())
    lines = [
        f"# Retraining round {summary['round_id']}",
        "",
        f"**{summary['outcome']}**",
        "",
        f"The gate: `{data.splits['gate']}` of `{data.data_root}` ({data.gate} held-out labeled "
        f"frames), moderate R40 AP in percent. A candidate is promoted only if neither its 2D "
        f"nor its 3D mAP is more than {drop:.1f} AP below the parent's "
        f"(`[retrain] max_map_drop`). Gate {'passed' if summary['passed'] else 'failed'}.",
        "",
        ap_table(parent, candidate, parent_name, name),
        "",
        "## Data",
        "",
        data_table(data),
        "",
        "## Training",
        "",
        f"{summary['steps']} steps of `{summary['method']}` teacher-student training from "
        f"version {summary['parent_version']}'s checkpoint (students and EMA teachers start "
        f"from its models). Started {summary['started_at']}."
        + (f" Time: {timings}." if timings else ""),
        "",
        f"![per-class AP of both models]({AP_PLOT})",
        "",
    ]
    markdown = directory / REPORT_MARKDOWN
    atomic_write_bytes(markdown, "\n".join(lines).encode())
    atomic_write_bytes(directory / REPORT_JSON, (json.dumps(summary, indent=2) + "\n").encode())
    return markdown
