"""`detmatch demo` at its smallest size: every stage runs for real (synthetic data, both
trainings, export, a `detmatch serve` process, gRPC labeling, a retraining round, the hot swap)
and the report holds its tables and pictures."""

from __future__ import annotations

import json
import re

from PIL import Image

from commands.main import main
from serving.repository import list_versions, served_version
from serving.store import list_frames


def test_demo_runs_the_whole_loop_and_reports(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--size", "smoke", "--out", str(out), "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    report = out / "report" / "report.md"
    assert printed.strip().splitlines()[-1] == f"report: {report}"
    text = report.read_text()
    verdict = re.search(r"\*\*DetMatch (beat|did not beat) labeled-only.*3D mAP ([\d.]+) vs "
                        r"([\d.]+).*2D mAP ([\d.]+) vs ([\d.]+)", text)  # fmt: skip
    assert verdict, text[:400]
    summary = json.loads((out / "report" / "demo.json").read_text())
    assert float(verdict[2]) == round(summary["detmatch"]["3d"]["mAP"], 1)
    assert float(verdict[3]) == round(summary["labeled_only"]["3d"]["mAP"], 1)
    for heading in ("## Labeled-only vs DetMatch", "## The service", "## Retraining round",
                    "## Training curves", "## Figure 3"):  # fmt: skip
        assert heading in text
    assert "| 3D | **mAP** |" in text and "| label store, machine-labeled" in text

    # The service labeled the unseen frames into the store; the round read them.
    assert summary["served"]["frames"] == 3 and summary["served"]["versions"] == ["000001"]
    assert [r.frame_id for r in list_frames(out / "store")] == ["new-000000", "new-000001",
                                                                "new-000002"]  # fmt: skip
    assert list_versions(out / "models") == ["000001", "000002"]
    round_result = summary["round"]
    assert round_result["version"] == "000002"
    if round_result["status"] == "promoted":
        assert served_version(out / "models") == "000002"
        assert summary["swap"]["answered_by"] == "000002"
    else:
        assert summary["swap"]["answered_by"] == "000001"

    for picture in [*summary["pictures"], "curves.png", "figure3.png", "per_class_ap.png"]:
        with Image.open(out / "report" / picture) as image:
            assert image.format == "PNG" and image.width > 200
        assert f"]({picture})" in text
    with Image.open(out / "report" / summary["pictures"][0]) as image:
        assert image.height > image.width / 2  # the image above a square bird's-eye view

    # A second demo into the same directory is refused before any work.
    assert main(["demo", "--size", "smoke", "--out", str(out)]) == 2
    assert "already exists and is not empty" in capsys.readouterr().err
