"""INT8 versions (export.quantize, `detmatch-export --quantize int8`): a separate version with
its own manifest record that the labeler serves, the first and last layers left float, and
a version whose labels agree with the fp32 version's less than required is refused with
nothing published."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import onnx
import pytest

from commands.export import main as export_main
from export.graphs import ExportCheckError
from export.quantize import float_layers, quantize_version
from serving.labeler import Labeler
from serving.repository import list_versions, served_version, verify_version
from tests.onnx_fixtures import exported_repository  # noqa: F401 - fixture


@pytest.fixture
def labeling_repository(tmp_path, exported_repository) -> Path:  # noqa: F811
    """The tiny exported version with thresholds that make it label (its scores are all
    below the manifest's): agreement is then measured on many labels."""
    repository = Path(shutil.copytree(exported_repository, tmp_path / "models"))
    manifest_path = repository / "000001" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["models"]["detector2d"]["score_threshold"] = 0.01
    manifest["models"]["detector3d"]["score_threshold"] = 0.01
    manifest["matching"]["tau_hung"] = 10.0
    manifest_path.write_text(json.dumps(manifest))
    return repository


def test_an_int8_version_is_published_beside_its_source_and_served(labeling_repository, synth_root):
    result = quantize_version(labeling_repository, "000001", synth_root, calibration_frames=3,
                              parity_frames=3, min_agreement=0.05)  # fmt: skip
    assert result.version == "000002" and list_versions(labeling_repository) == ["000001", "000002"]
    record = result.record
    assert record.source_version == "000001" and record.matched_labels > 10
    assert 0.05 <= record.agreement < 1.0  # quantized: close, not identical
    manifest = verify_version(result.path)
    assert manifest.format == 3 and manifest.quantization == record
    source = Labeler(labeling_repository / "000001")
    assert manifest.files != source.manifest.files  # its own graphs and checksums
    quantized = Labeler(result.path)
    assert quantized.version == "000002" and quantized.classes == source.classes
    for spec in (manifest.model_2d, manifest.model_3d):
        graph = onnx.load(str(result.path / spec.file)).graph
        ops = {node.op_type for node in graph.node}
        assert {"QuantizeLinear", "DequantizeLinear"} <= ops
        # the layers float_layers names keep float weights: no DequantizeLinear feeds them
        dequantized = {o for n in graph.node if n.op_type == "DequantizeLinear" for o in n.output}
        kept = [n for n in graph.node if n.name in float_layers(labeling_repository / "000001"
                                                                / spec.file)]  # fmt: skip
        assert kept and all(n.input[1] not in dequantized for n in kept)
    assert served_version(labeling_repository) == "000001"  # promotion is a separate step


def test_an_int8_version_that_disagrees_is_refused_and_nothing_published(
    labeling_repository, synth_root, capsys
):
    with pytest.raises(ExportCheckError, match="below the 100% required"):
        quantize_version(labeling_repository, "000001", synth_root, calibration_frames=3,
                         parity_frames=3, min_agreement=1.0)  # fmt: skip
    assert list_versions(labeling_repository) == ["000001"]
    assert not list(labeling_repository.glob(".staging*"))
    code = export_main(["--repository", str(labeling_repository), "--from-version", "000001",
                        "--quantize", "int8", "--calibration-data", str(synth_root),
                        "--calibration-frames", "3", "--agreement-frames", "3",
                        "--min-agreement", "1.0"])  # fmt: skip
    assert code == 1
    assert "the INT8 version failed its check, nothing was published" in capsys.readouterr().err
    assert list_versions(labeling_repository) == ["000001"]
    code = export_main(["--repository", str(labeling_repository), "--from-version", "000001",
                        "--quantize", "int8", "--calibration-data", str(synth_root),
                        "--calibration-frames", "3", "--agreement-frames", "3",
                        "--min-agreement", "0.05", "--promote"])  # fmt: skip
    assert code == 0 and served_version(labeling_repository) == "000002"
    assert "published and promoted INT8 version 000002 of 000001" in capsys.readouterr().out
    assert export_main(["--repository", str(labeling_repository), "--from-version",
                        "000002", "--quantize", "int8", "--calibration-data",
                        str(synth_root)]) == 2  # fmt: skip
    assert "quantized already" in capsys.readouterr().err
