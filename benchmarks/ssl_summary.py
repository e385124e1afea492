"""Mean and per-seed moderate R40 mAP of several ssl_benchmark.py reports (one per split seed).

    python benchmarks/ssl_summary.py runs/ssl_gpu/s*/ssl_benchmark.json

Prints, per modality, one row per method: the mAP of each report, their mean, and the mean
gain over labeled-only; then the pseudo-label precision / recall of each rule per report.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path, help="ssl_benchmark.json files")
    args = parser.parse_args()
    reports = [json.loads(path.read_text()) for path in args.reports]
    names = [path.parent.name for path in args.reports]
    methods: list[str] = []
    for report in reports:
        methods += [m for m in report["results"] if m not in methods]
    for modality in ("3d", "2d", "bev"):
        print(f"\n{modality.upper()} mAP (moderate R40)")
        print("| method | " + " | ".join(names) + " | mean | mean gain |")
        print("|---|" + "---|" * (len(names) + 2))
        for method in methods:
            values, gains = [], []
            for report in reports:
                row = report["results"].get(method)
                values.append(None if row is None else row[modality]["mAP"])
                if row is not None:
                    gains.append(
                        row[modality]["mAP"] - report["results"]["labeled-only"][modality]["mAP"]
                    )
            present = [v for v in values if v is not None]
            cells = ["-" if v is None else f"{v:.1f}" for v in values]
            mean = sum(present) / len(present)
            gain = sum(gains) / len(gains)
            print(f"| {method} | " + " | ".join(cells) + f" | {mean:.1f} | {gain:+.1f} |")
    print("\nPseudo-labels of the pre-trained teacher, Car precision / recall")
    print("| rule | modality | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for rule in ("confidence", "detmatch"):
        for modality in ("3d", "2d"):
            cells = []
            for report in reports:
                quality = report["pseudo_label_quality"][rule]["Car"][modality]
                cells.append(f"{quality['precision']:.3f} / {quality['recall']:.3f}")
            print(f"| {rule} | {modality} | " + " | ".join(cells) + " |")
    print("\nrerun: python benchmarks/ssl_summary.py " + " ".join(map(str, args.reports)))


if __name__ == "__main__":
    main()
