"""Mean and per-seed results of several ssl_benchmark.py reports (one per split seed).

    python benchmarks/ssl_summary.py runs/ssl/s*/ssl_benchmark.json [--split val|dev]

Prints, per modality, one row per method: moderate R40 mAP of each seed, their mean, and the
mean gain over the better of labeled-only and its EMA control (per seed); per-class means;
then the pseudo-label precision / recall / F1 of each rule and class, pooled over the
seeds, each seed's Figure-3 Spearman correlations and, where the reports have it, each seed's
Figure 4 (image-plane AP of both modalities by occlusion level).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from detmatch.eval.pseudo_labels import pooled_precision_recall_f1

BASELINES = ("labeled-only", "control")


def baseline(results: dict, modality: str) -> float:
    """The better labeled-only row of one report (what a gain is measured against)."""
    return max(results[b][modality]["mAP"] for b in BASELINES if b in results)


def pooled_quality(reports: list[dict], rule: str, name: str, modality: str) -> str:
    """Precision / recall / F1, as text, of one rule, class and modality over all reports."""
    rows = [report["pseudo_label_quality"][rule][name][modality] for report in reports]
    return " / ".join(f"{value:.3f}" for value in pooled_precision_recall_f1(rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path, help="ssl_benchmark.json files")
    parser.add_argument("--split", default="val", choices=("val", "dev"))
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
    print("\nrerun: python benchmarks/ssl_summary.py " + " ".join(map(str, args.reports)))


if __name__ == "__main__":
    main()
