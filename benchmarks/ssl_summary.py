"""Mean and per-seed results of several ssl_benchmark.py reports (one per split seed).

    python -m benchmarks.ssl_summary runs/ssl/s*/ssl_benchmark.json [--split val|dev]

Prints, per modality, one row per method: moderate R40 mAP of each seed, their mean, and the
mean gain over the better of labeled-only and its EMA control (per seed); per-class means;
then the pseudo-label precision / recall / F1 of each rule and class, pooled over the
seeds, each seed's Figure-3 Spearman correlations and, where the reports have it, each seed's
Figure 4 (image-plane AP of both modalities by occlusion level); last, the issue-14 targets
of --method (default detmatch): each gain per seed, its mean, the goal, met or missed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from benchmarks.harness import benchmark_parser, rerun
from detmatch.eval.pseudo_labels import pooled_precision_recall_f1

BASELINES = ("labeled-only", "control")


def baseline(results: dict, modality: str, score: str = "mAP") -> float:
    """The better labeled-only row of one report (what a gain is measured against)."""
    return max(results[b][modality][score] for b in BASELINES if b in results)


@dataclass(frozen=True)
class GainTarget:
    """A method's gain in one modality and score (mAP or a class's AP) over a reference run
    (another method; None: the better labeled-only row), as a mean over seeds, and the least
    gain that meets it."""

    modality: str
    score: str
    reference: str | None
    goal: float

    @property
    def name(self) -> str:
        return self.reference or "the better labeled-only row"

    def gain(self, results: dict, method: str) -> float | None:
        """The gain on one seed's results; None where the seed lacks a run it needs."""
        if method not in results:
            return None
        if self.reference is None:
            if not any(b in results for b in BASELINES):
                return None
            reference = baseline(results, self.modality, self.score)
        elif self.reference in results:
            reference = results[self.reference][self.modality][self.score]
        else:
            return None
        return results[method][self.modality][self.score] - reference


# Issue 14's targets (val, mean of the split seeds).
GAIN_TARGETS = (
    GainTarget("3d", "mAP", None, 5.0),
    GainTarget("3d", "mAP", "confidence", 1.0),
    GainTarget("2d", "mAP", None, 3.0),
    GainTarget("2d", "mAP", "confidence", 3.0),
    GainTarget("3d", "Pedestrian", "confidence", 3.0),
)


def gain_target_rows(results: list[dict], method: str) -> list[list[str]]:
    """One table row per gain target: name, each seed's gain, the mean, the goal, verdict."""
    rows = []
    for target in GAIN_TARGETS:
        gains = [target.gain(result, method) for result in results]
        known = [g for g in gains if g is not None]
        mean = sum(known) / len(known) if known else None
        verdict = "-" if mean is None else "met" if mean >= target.goal else "missed"
        if mean is not None and len(known) < len(gains):
            verdict += f" ({len(known)} of {len(gains)} seeds)"
        rows.append([
            f"{target.modality.upper()} {target.score}: {method} - {target.name}",
            *("-" if g is None else f"{g:+.1f}" for g in gains),
            "-" if mean is None else f"{mean:+.1f}",
            f">= {target.goal:+.1f}",
            verdict,
        ])  # fmt: skip
    return rows


def pseudo_label_verdicts(reports: list[dict], method: str, classes: list[str]) -> list[str]:
    """Issue 14's pseudo-label target: the method's pooled precision and F1 above confidence
    thresholding's, per modality and class; one line per modality."""
    lines = []
    for modality in ("3d", "2d"):
        above = {"precision": [], "F1": []}
        for name in classes:
            ours, theirs = (
                pooled_precision_recall_f1(
                    [report["pseudo_label_quality"][rule][name][modality] for report in reports]
                )
                for rule in (method, "confidence")
            )  # fmt: skip
            for measure, index in (("precision", 0), ("F1", 2)):
                above[measure].append(name if ours[index] > theirs[index] else f"not {name}")
        met = all(not n.startswith("not ") for names in above.values() for n in names)
        lines.append(f"- {modality.upper()} pseudo-labels, {method} above confidence: "
                     f"precision {', '.join(above['precision'])}; F1 {', '.join(above['F1'])}: "
                     f"{'met' if met else 'missed'}")  # fmt: skip
    return lines


def pooled_quality(reports: list[dict], rule: str, name: str, modality: str) -> str:
    """Precision / recall / F1, as text, of one rule, class and modality over all reports."""
    rows = [report["pseudo_label_quality"][rule][name][modality] for report in reports]
    return " / ".join(f"{value:.3f}" for value in pooled_precision_recall_f1(rows))


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("reports", nargs="+", type=Path, help="ssl_benchmark.json files")
    parser.add_argument("--split", default="val", choices=("val", "dev"))
    parser.add_argument("--method", default="detmatch", help="the method the targets judge")
    args = parser.parse_args()
    reports = [json.loads(path.read_text()) for path in args.reports]
    names = [f"seed {report['seed']}" for report in reports]
    results = [report["results"][args.split] for report in reports]
    methods: list[str] = []
    for result in results:
        methods += [m for m in result if m not in methods]
    classes = [c for c in next(iter(results[0].values()))["3d"] if c != "mAP"]
    for modality in ("3d", "2d"):
        print(f"\n{args.split}: {modality.upper()} mAP (moderate R40), gain over the better of "
              "labeled-only and its control")  # fmt: skip
        print("| method | " + " | ".join(names) + " | mean | " + " | ".join(classes)
              + " | mean gain |")  # fmt: skip
        print("|---|" + "---|" * (len(names) + len(classes) + 2))
        for method in methods:
            rows = [r[method][modality] for r in results if method in r]
            cells = [f"{r[method][modality]['mAP']:.1f}" if method in r else "-" for r in results]
            mean = sum(row["mAP"] for row in rows) / len(rows)
            per_class = [sum(row[c] for row in rows) / len(rows) for c in classes]
            gains = [r[method][modality]["mAP"] - baseline(r, modality) for r in results
                     if method in r]  # fmt: skip
            gain = "" if method in BASELINES else f"{sum(gains) / len(gains):+.1f}"
            print(f"| {method} | " + " | ".join(cells) + f" | {mean:.1f} | "
                  + " | ".join(f"{v:.1f}" for v in per_class) + f" | {gain} |")  # fmt: skip
    print("\nPseudo-labels of the pre-trained teachers, precision / recall / F1 pooled over the "
          "seeds (true positives, pseudo-labels and objects summed)")  # fmt: skip
    print("| rule | modality | " + " | ".join(classes) + " |")
    print("|---|---|" + "---|" * len(classes))
    for rule in ("confidence", "detmatch"):
        for modality in ("3d", "2d"):
            cells = [pooled_quality(reports, rule, name, modality) for name in classes]
            print(f"| {rule} | {modality} | " + " | ".join(cells) + " |")
    print("\nFigure 3: Spearman correlation of true IoU with the max class score / the negated "
          "matching cost")  # fmt: skip
    for name, report in zip(names, reports, strict=True):
        rho = report.get("figure3") or {}
        if rho:
            print(f"- {name}: score {rho['spearman_iou_score']:.3f}, "
                  f"cost {rho['spearman_iou_negative_cost']:.3f}")  # fmt: skip
    if all(report.get("figure4_pr") for report in reports):
        print("\nFigure 4 (the paper's): image-plane AP of the pre-trained 2D / 3D detectors by "
              "occlusion level, per seed")  # fmt: skip
        print("| class | occlusion | " + " | ".join(names) + " |")
        print("|---|---|" + "---|" * len(names))
        for name, levels in reports[0]["figure4_pr"].items():
            for level in levels:
                rows = [report["figure4_pr"][name][level] for report in reports]
                cells = [f"{row['2d']:.1f} / {row['3d']:.1f}" for row in rows]
                print(f"| {name} | {level} | " + " | ".join(cells) + " |")
    print_targets(reports, results, names, classes, args.method, args.split)
    print(f"\nrerun: {rerun('ssl_summary')}")


def print_targets(
    reports: list[dict],
    results: list[dict],
    names: list[str],
    classes: list[str],
    method: str,
    split: str,
) -> None:
    """Issue 14's targets for one method (set on val): gains per seed and their mean on
    `split`, then pseudo-label precision and F1 against confidence thresholding, then Figure
    3's ranking."""
    print(f"\nTargets (issue 14, set on val) for {method} on {split}: gain per seed, mean over "
          "seeds, goal")  # fmt: skip
    print("| target | " + " | ".join(names) + " | mean | goal | verdict |")
    print("|---|" + "---|" * (len(names) + 3))
    for row in gain_target_rows(results, method):
        print("| " + " | ".join(row) + " |")
    if all(method in report["pseudo_label_quality"] for report in reports):
        for line in pseudo_label_verdicts(reports, method, classes):
            print(line)
    rhos = [report.get("figure3") or {} for report in reports]
    if all(rhos):
        ranked = [rho["spearman_iou_negative_cost"] > rho["spearman_iou_score"] for rho in rhos]
        print(
            f"- Figure 3, the matching cost ranks true IoU better than the max class score: "
            f"{sum(ranked)} of {len(ranked)} seeds: {'met' if all(ranked) else 'missed'}"
        )


if __name__ == "__main__":
    main()
