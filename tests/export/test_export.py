import dataclasses
import re

import numpy as np
import onnx
import pytest

from commands.export import main as export_main
from detmatch.checkpoints import resolve_checkpoint
from detmatch.data.kitti import KittiDataset
from detmatch.matching_policy import MatchingPolicy
from detmatch.models.build import load_detectors
from export.onnx_export import export_checkpoint
from export.parity import ParityError, PeakTies, Tolerance, check_parity, compare_decoded
from serving.manifest import FileRecord, PillarGridSpec, TensorSpec
from serving.repository import (
    CHECKPOINT_FILE,
    MODEL_2D_FILE,
    MODEL_3D_FILE,
    RepositoryError,
    list_versions,
    load_manifest,
    served_version,
    training_checkpoint,
    verify_checksums,
)
from serving.sessions import make_session
from tests.conftest import KITTI_SAMPLE


def test_export_publishes_a_checked_promoted_version(exported_repository):
    assert list_versions(exported_repository) == ["000001"]
    assert served_version(exported_repository) == "000001"
    version = exported_repository / "000001"
    for name in (MODEL_2D_FILE, MODEL_3D_FILE):
        model = onnx.load(str(version / name))
        onnx.checker.check_model(model, full_check=True)
        assert max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17
    assert not [p for p in exported_repository.iterdir() if p.name.startswith(".")]


def test_manifest_describes_models_thresholds_training_and_files(exported_repository):
    version = exported_repository / "000001"
    manifest = load_manifest(version)
    verify_checksums(version, manifest)
    assert manifest.version == "000001"
    assert manifest.classes == ("Car", "Pedestrian", "Cyclist")
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", manifest.exported_at)
    spec_2d, spec_3d = manifest.model_2d, manifest.model_3d
    assert spec_2d.inputs == (TensorSpec("image", "uint8", ("batch", "height", "width", 3)),)
    assert [(i.name, i.shape) for i in spec_3d.inputs] == [
        ("features", ("batch", "pillars", 8, 9)),
        ("coords", ("batch", "pillars", 2)),
        ("num_points", ("batch", "pillars")),
    ]
    assert spec_2d.outputs[0] == TensorSpec("boxes", "float32", ("batch", 30, 4))
    assert spec_3d.outputs[0] == TensorSpec("boxes", "float32", ("batch", 30, 7))
    assert spec_2d.preprocessing.in_graph and spec_2d.preprocessing.input_size == (320, 96)
    assert spec_3d.preprocessing.grid == PillarGridSpec(
        point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 1.0),
        pillar_size=(0.4, 0.4),
        max_points_per_pillar=8,
        max_pillars=6000,
    )
    assert spec_2d.score_threshold == spec_3d.score_threshold == 0.1
    assert manifest.matching.tau_hung == -1.5
    assert manifest.matching.tau_3d_outside_view == 0.3
    # The training's in-view LiDAR-only rule, as the policy holds it (1.0 in the config: off,
    # None; the default 0.6).
    unmatched = manifest.training.config["ssl"]["tau_3d_unmatched"]
    assert manifest.matching.tau_3d_unmatched == (None if unmatched == 1.0 else unmatched) == 0.6
    assert manifest.matching.policy == MatchingPolicy(-1.5, 0.3, 0.6)
    training = manifest.training
    assert training.step == 6 and tuple(training.data["classes"]) == manifest.classes
    assert len(training.checkpoint_sha256) == 64
    assert "mAP" in training.metrics["3d"]
    assert set(manifest.files) == {MODEL_2D_FILE, MODEL_3D_FILE}
    assert {"torch", "onnx", "onnxruntime", "numpy", "exporter"} <= set(manifest.tools)
    parity = manifest.parity
    assert parity["passed"] and parity["rtol"] == 1e-4 and parity["atol"] == 1e-3
    sources = {f["source"] for f in parity["frames"]}
    assert str(KITTI_SAMPLE) in sources and any(s.startswith("synthetic") for s in sources)
    sizes = {tuple(f["image_size"]) for f in parity["frames"]}
    assert (621, 188) in sizes and (1242, 375) in sizes  # synthetic half and full resolution
    assert all(f["paired"]["3d"] + f["unpaired_at_cut"]["3d"] >= 29 for f in parity["frames"])


def test_onnxruntime_matches_pytorch_on_other_frames(
    exported_repository, trained_checkpoint, synth_root
):
    """Parity again, on frames the export did not check, including a tiny odd-sized image."""
    loaded = load_detectors(trained_checkpoint)
    config, model_2d, model_3d = loaded.config, loaded.model_2d, loaded.model_3d
    version = exported_repository / "000001"
    frames = [("synth", KittiDataset(synth_root).load_frame(i)) for i in ("000003", "000004")]
    report = check_parity(
        make_session(version / MODEL_2D_FILE),
        make_session(version / MODEL_3D_FILE),
        model_2d,
        model_3d,
        config,
        frames,
        Tolerance(),
    )
    assert report.passed, report.summary()
    errors = report.max_abs_error()
    assert errors["2d/heatmap"] < 1e-4 and errors["3d/heatmap"] < 1e-4
    assert errors["2d/boxes"] < 1e-2 and errors["3d/boxes"] < 1e-3


def _decoded(boxes, scores, classes):
    probabilities = np.zeros((len(scores), 3), dtype=np.float32)
    probabilities[np.arange(len(scores)), classes] = scores
    return {
        "boxes": np.asarray(boxes, dtype=np.float32),
        "scores": np.asarray(scores, dtype=np.float32),
        "classes": np.asarray(classes, dtype=np.int64),
        "probabilities": probabilities,
    }


def test_decoded_detections_pair_as_sets_and_only_near_ties_are_excused():
    boxes = np.arange(16, dtype=np.float32).reshape(4, 4) * 10
    reference = _decoded(boxes, [0.9, 0.8, 0.5, 0.3], [0, 1, 2, 0])
    tolerance = Tolerance()
    # The same detections in another order, within tolerance: all paired, reordered counted.
    order = [1, 0, 2, 3]
    value = _decoded(
        boxes[order] + 1e-4, np.array([0.8, 0.9, 0.5, 0.3])[[0, 1, 2, 3]], [1, 0, 2, 0]
    )
    counts, problems = compare_decoded("2d", reference, value, tolerance)
    assert not problems and counts["paired"] == 4 and counts["reordered"] == 2
    # The last one swapped for a near tie at the top-k cut: excused.
    value = _decoded(np.concatenate([boxes[:3], [[500, 500, 600, 600]]]), [0.9, 0.8, 0.5, 0.3005],
                     [0, 1, 2, 0])  # fmt: skip
    counts, problems = compare_decoded("2d", reference, value, tolerance)
    assert not problems and counts["unpaired_at_cut"] == 2
    # A confident detection missing: a problem, named.
    value = _decoded(np.concatenate([boxes[:1], [[500, 500, 600, 600]], boxes[2:]]),
                     [0.9, 0.3, 0.5, 0.3], [0, 1, 2, 0])  # fmt: skip
    counts, problems = compare_decoded("2d", reference, value, tolerance)
    assert len(problems) == 1 and "PyTorch detection 1 (class 1, score 0.800000" in problems[0]
    # ... unless its pixel is a near tie at the 3x3 peak test of its own heatmap.
    heat = np.zeros((3, 5, 5))
    heat[1, 2, 2], heat[1, 2, 3] = 0.8, 0.8 + 1e-8
    ties = (PeakTies(heat, margin=1e-7), PeakTies(np.zeros((3, 5, 5)), margin=1e-7))
    counts, problems = compare_decoded("2d", reference, value, tolerance, ties)
    assert not problems and counts["unpaired_at_peak"] == 1
    # Probabilities of a pair must agree too.
    value = _decoded(boxes, [0.9, 0.8, 0.5, 0.3], [0, 1, 2, 0])
    value["probabilities"][0, 1] = 0.2
    _, problems = compare_decoded("2d", reference, value, tolerance)
    assert problems == ["2d: probabilities of detection 0 differ beyond tolerance"]


def _no_version_and_no_staging(repository):
    return list_versions(repository) == [] and not any(repository.iterdir())


def test_export_failing_parity_exits_nonzero_and_publishes_nothing(
    trained_checkpoint, synth_root, tmp_path, capsys
):
    repository = tmp_path / "models"
    code = export_main(
        ["--checkpoint", str(trained_checkpoint), "--repository", str(repository),
         "--synthetic-frames", "0", "--parity-data", str(synth_root), "--parity-frames", "1",
         "--rtol", "0", "--atol", "0", "--promote"]
    )  # fmt: skip
    assert code == 1
    error = capsys.readouterr().err
    assert "export failed, nothing was published" in error and "disagreements beyond" in error
    assert _no_version_and_no_staging(repository)


def test_export_failing_midway_leaves_no_version(
    trained_checkpoint, synth_root, tmp_path, monkeypatch
):
    """The ONNX files and parity are done, then writing the manifest fails."""
    import export.onnx_export

    def broken_manifest(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(export.onnx_export, "build_manifest", broken_manifest)
    repository = tmp_path / "models"
    with pytest.raises(OSError, match="disk full"):
        export_checkpoint(trained_checkpoint, repository, synthetic_frames=0,
                          parity_data=[synth_root], parity_frames_per_source=1)  # fmt: skip
    assert _no_version_and_no_staging(repository)


def test_parity_error_is_raised_by_the_api(trained_checkpoint, synth_root, tmp_path):
    with pytest.raises(ParityError, match="onnxruntime disagrees with PyTorch"):
        export_checkpoint(trained_checkpoint, tmp_path / "models", synthetic_frames=0,
                          parity_data=[synth_root], parity_frames_per_source=1,
                          tolerance=Tolerance(0.0, 0.0))  # fmt: skip
    assert _no_version_and_no_staging(tmp_path / "models")


def test_cli_exports_next_version_lists_promotes_and_demotes(
    exported_repository, trained_checkpoint, synth_root, tmp_path, capsys
):
    import shutil

    repository = tmp_path / "models"
    shutil.copytree(exported_repository, repository)
    args = [
        "--checkpoint", str(trained_checkpoint), "--repository", str(repository),
        "--synthetic-frames", "0", "--parity-data", str(synth_root), "--parity-frames", "1",
    ]  # fmt: skip
    assert export_main([*args, "--quiet", "--no-checkpoint"]) == 0
    assert "published (not promoted) version 000002" in capsys.readouterr().out
    assert list_versions(repository) == ["000001", "000002"]
    assert served_version(repository) == "000001"
    assert load_manifest(repository / "000002").version == "000002"
    # --no-checkpoint: the manifest references the checkpoint (verified) and keeps no copy.
    assert load_manifest(repository / "000002").training.checkpoint_file is None
    assert not (repository / "000002" / CHECKPOINT_FILE).exists()
    assert training_checkpoint(repository / "000002") == resolve_checkpoint(trained_checkpoint)
    assert (repository / "000001" / CHECKPOINT_FILE).is_file()
    # An explicit version that exists is refused before any work.
    assert export_main([*args, "--version", "2"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert export_main(["--repository", str(repository), "--promote", "2"]) == 0
    assert served_version(repository) == "000002"
    assert export_main(["--repository", str(repository), "--list"]) == 0
    listing = capsys.readouterr().out
    assert "000002" in listing and "served" in listing
    assert export_main(["--repository", str(repository), "--demote", "000002"]) == 0
    assert served_version(repository) == "000001"
    assert export_main(["--repository", str(repository), "--promote", "7"]) == 2
    with pytest.raises(SystemExit):
        export_main(["--repository", str(repository)])
    manifest = load_manifest(repository / "000002")
    assert manifest.parity["frames"][0]["source"] == str(synth_root)
    wrong = {**manifest.files, MODEL_2D_FILE: FileRecord(sha256="0" * 64, bytes=1)}
    with pytest.raises(RepositoryError):
        verify_checksums(repository / "000002", dataclasses.replace(manifest, files=wrong))
