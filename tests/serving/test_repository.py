import dataclasses
import json
import os
import shutil
from pathlib import Path

import pytest

from detmatch.files import sha256_file
from detmatch.matching_policy import MatchingPolicy
from detmatch.pseudo_labels import match_detections
from detmatch.records import to_plain
from serving.manifest import (
    MATCHING_FUNCTION,
    GateFigures,
    Manifest,
    ManifestError,
    MatchingSpec,
    RetrainingRecord,
    RoundData,
    gate_passes,
)
from serving.repository import (
    CHECKPOINT_FILE,
    RepositoryError,
    demote,
    file_record,
    list_versions,
    load_manifest,
    next_version,
    parse_version,
    promote,
    promoted_versions,
    publish,
    served_version,
    staging_directory,
    training_checkpoint,
    verify_checksums,
)
from tests.manifests import minimal_manifest


def _publish(root, payload=b"model", version=None):
    """A minimal version through the real staging + publish path."""
    with staging_directory(root) as staging:
        (staging / "model.onnx").write_bytes(payload)

        def manifest(name):
            minimal_manifest(name, {"model.onnx": file_record(staging / "model.onnx")}).save(
                staging
            )

        return publish(root, staging, version, finalize=manifest)


def test_versions_are_numbered_ordered_and_immutable(tmp_path):
    root = tmp_path / "models"
    assert _publish(root)[0] == "000001"
    assert _publish(root)[0] == "000002"
    assert _publish(root, version=10)[0] == "000010"
    assert _publish(root)[0] == "000011"
    (root / "notes").mkdir()
    (root / ".staging-killed").mkdir()
    assert list_versions(root) == ["000001", "000002", "000010", "000011"]
    assert next_version(root) == "000012"
    with pytest.raises(RepositoryError, match="already exists"):
        _publish(root, version="000010")
    assert sorted(p.name for p in root.iterdir() if p.name.startswith(".")) == [".staging-killed"]
    assert load_manifest(root / "000010").version == "000010"
    verify_checksums(root / "000010")
    assert parse_version("7") == parse_version(7) == "000007"
    for bad in ("-1", "v2", "0", "1.5"):
        with pytest.raises(RepositoryError):
            parse_version(bad)
    with pytest.raises(FileNotFoundError):
        list_versions(tmp_path / "missing")


def test_the_newest_promoted_version_serves_and_demotion_rolls_back(tmp_path):
    root = tmp_path / "models"
    for _ in range(3):
        _publish(root)
    assert served_version(root) is None
    promote(root, 1)
    promote(root, "000002")
    assert promoted_versions(root) == ["000001", "000002"]
    assert served_version(root) == "000002"
    demote(root, 2)
    assert served_version(root) == "000001"
    assert json.loads((root / "000001" / "PROMOTED").read_text())["promoted_at"]
    with pytest.raises(FileNotFoundError):
        promote(root, 4)


def test_checksums_and_manifest_are_checked(tmp_path):
    root = tmp_path / "models"
    _, path = _publish(root)
    (path / "model.onnx").write_bytes(b"other")
    with pytest.raises(RepositoryError, match="does not match its checksum"):
        verify_checksums(path)
    (path / "model.onnx").unlink()
    with pytest.raises(RepositoryError, match="missing"):
        verify_checksums(path)
    (path / "manifest.json").write_text('{"format": 99}')
    with pytest.raises(RepositoryError, match="format 99"):
        load_manifest(path)
    (path / "manifest.json").write_text("{")
    with pytest.raises(RepositoryError, match="not valid JSON"):
        load_manifest(path)


def test_a_failed_staging_leaves_nothing_and_stale_staging_is_swept(tmp_path):
    root = tmp_path / "models"
    with pytest.raises(RuntimeError), staging_directory(root) as staging:
        (staging / "detector2d.onnx").write_bytes(b"half")
        raise RuntimeError("export failed")
    assert list(root.iterdir()) == []
    stale = root / ".staging-old"
    stale.mkdir()
    os.utime(stale, (0, 0))
    with staging_directory(root):
        pass
    assert list(root.iterdir()) == []


def test_the_manifest_round_trips_and_its_errors_name_the_field(tmp_path):
    root = tmp_path / "models"
    _, path = _publish(root)
    manifest = load_manifest(path)
    manifest.save(tmp_path)
    assert load_manifest(tmp_path) == manifest
    data = json.loads((path / "manifest.json").read_text())
    data["models"]["detector3d"]["preprocessing"]["grid"]["pillar_size"] = [0.5, 0.5, 0.5]
    with pytest.raises(
        ManifestError, match=r"models\.detector3d\.preprocessing\.grid\.pillar_size"
    ):
        Manifest.from_json(data)
    data = json.loads((path / "manifest.json").read_text())
    data["matching"]["tau_3d_unmatched"] = 1.0
    with pytest.raises(
        ManifestError, match=r"matching: tau_3d_unmatched: expected a probability threshold in"
    ):
        Manifest.from_json(data)
    del data["matching"]["tau_3d_unmatched"]  # a manifest from before the field: off
    assert Manifest.from_json(data).matching.tau_3d_unmatched is None
    data["matching"]["tau_3d_outside_view"] = 1.5
    with pytest.raises(ManifestError, match=r"matching: tau_3d_outside_view: expected a prob"):
        Manifest.from_json(data)
    del data["matching"]["function"]
    with pytest.raises(ManifestError, match="missing field 'function'"):
        Manifest.from_json(data)
    data = json.loads((path / "manifest.json").read_text())
    data["files"]["../escape.onnx"] = data["files"]["model.onnx"]
    with pytest.raises(ManifestError, match="is not plain"):
        Manifest.from_json(data)
    data = json.loads((path / "manifest.json").read_text())
    data["models"]["detector2d"]["max_detections"] = 2.5
    with pytest.raises(ManifestError, match=r"models\.detector2d\.max_detections must be int"):
        Manifest.from_json(data)
    (path / "manifest.json").write_text(json.dumps({**data, "extra": 1}))
    with pytest.raises(RepositoryError, match="unknown field 'extra'"):
        load_manifest(path)


def _figures(ap_3d: float, ap_2d: float = 10.0) -> GateFigures:
    return GateFigures(
        ap_2d={"Car": ap_2d, "mAP": ap_2d}, ap_3d={"Car": ap_3d, "mAP": ap_3d},
        ap_bev={"Car": ap_3d, "mAP": ap_3d},
    )  # fmt: skip


def _round_record(candidate: GateFigures, parent: GateFigures, passed: bool) -> dict:
    """A round record as JSON, its `passed` as given (right or not)."""
    data = RoundData(2, 3, 4, 5, 1, "a" * 64, "pool", "/data", {"gate": "val"})
    right = gate_passes(candidate, parent, 1.0)
    record = RetrainingRecord("r1", "000001", "2026-01-01T00:00:00Z", "detmatch", 10, 1.0,
                              candidate, parent, right, data, {})  # fmt: skip
    return {**to_plain(record), "passed": passed}


def test_the_matching_policy_round_trips_through_the_manifest_in_the_keys_it_always_had(
    tmp_path,
):
    """Export writes the policy as the `matching` table (the same keys and values as every
    version before it), serving reads it back as the same policy; older tables still load."""
    policy = MatchingPolicy(tau_hung=-2.0, tau_3d_outside_view=0.3, tau_3d_unmatched=0.6)
    manifest = dataclasses.replace(
        minimal_manifest("000001", {"model.onnx": file_record(_placeholder(tmp_path))}),
        matching=MatchingSpec.of(policy),
    )
    manifest.save(tmp_path)
    stored = json.loads((tmp_path / "manifest.json").read_text())["matching"]
    assert list(stored.items()) == [
        ("tau_hung", -2.0),
        ("tau_3d_outside_view", 0.3),
        ("function", "detmatch.pseudo_labels.match_detections"),
        ("tau_3d_unmatched", 0.6),
    ]
    assert MATCHING_FUNCTION == f"{match_detections.__module__}.{match_detections.__name__}"
    assert Manifest.load(tmp_path).matching.policy == policy
    # A table written before tau_3d_unmatched, with the fallback off: the paper's matching only.
    old = {"tau_hung": -1.5, "tau_3d_outside_view": None, "function": MATCHING_FUNCTION}
    data = {**manifest.to_json(), "matching": old}
    assert Manifest.from_json(data).matching.policy == MatchingPolicy(-1.5, None, None)
    data["matching"] = {**old, "tau_hung": float("nan")}
    with pytest.raises(ManifestError, match="matching: tau_hung: expected a finite number"):
        Manifest.from_json(data)


def _placeholder(directory: Path) -> Path:
    path = directory / "model.onnx"
    path.write_bytes(b"model")
    return path


def test_manifest_format_1_is_read_and_format_2_fields_are_checked(tmp_path):
    record = file_record(_write(tmp_path / "model.onnx"))
    plain = minimal_manifest("000002", {"model.onnx": record}).to_json()
    old = {**plain, "format": 1}
    del old["retraining"]
    del old["training"]["checkpoint_file"]
    assert Manifest.from_json(old).format == 1  # written before retraining rounds
    with pytest.raises(ManifestError, match="a format 1 manifest has no retraining record"):
        Manifest.from_json({**old, "training": {**old["training"], "checkpoint_file": "c.pt"}})
    with pytest.raises(ManifestError, match="this reader knows 1, 2, 3"):
        Manifest.from_json({**plain, "format": 4})
    with pytest.raises(ManifestError, match="format 3, and only format 3, has a quantization"):
        Manifest.from_json({**plain, "format": 3})  # an INT8 version's format, without its record

    passed = _round_record(_figures(30.0), _figures(30.5), passed=True)  # within 1 point
    manifest = Manifest.from_json({**plain, "retraining": passed})
    assert manifest.retraining.parent_version == "000001" and manifest.retraining.passed
    assert gate_passes(_figures(30.0), _figures(30.5), 1.0)
    assert not gate_passes(_figures(30.0), _figures(31.5), 1.0)  # 3D fell 1.5
    assert not gate_passes(_figures(40.0, ap_2d=5.0), _figures(30.0), 1.0)  # 2D fell 5
    contradicted = _round_record(_figures(20.0), _figures(30.0), passed=True)
    with pytest.raises(ManifestError, match="retraining.*passed: True contradicts the figures"):
        Manifest.from_json({**plain, "retraining": contradicted})
    own_parent = _round_record(_figures(20.0), _figures(20.0), passed=True)
    with pytest.raises(ManifestError, match="parent_version: 000002 is this version"):
        Manifest.from_json({**plain, "version": "000002", "retraining": {**own_parent,
                            "parent_version": "000002"}})  # fmt: skip
    too_high = _round_record(_figures(30.0), _figures(20.0), passed=True)
    too_high["candidate"]["ap_3d"]["Car"] = 101.0
    with pytest.raises(ManifestError, match=r"retraining.candidate: ap_3d.Car must be an AP in"):
        Manifest.from_json({**plain, "retraining": too_high})
    with pytest.raises(ManifestError, match="checkpoint_file must be a plain file name"):
        Manifest.from_json({**plain, "training": {**plain["training"],
                            "checkpoint_file": "../x.pt"}})  # fmt: skip


def _write(path, data: bytes = b"bytes"):
    path.write_bytes(data)
    return path


def test_training_checkpoint_is_verified(tmp_path, exported_repository):
    """The version keeps its checkpoint (its SHA-256 in the manifest); a format 1 version or
    an export without the copy only references it; either is checked before use."""
    version = exported_repository / "000001"
    manifest = load_manifest(version)
    assert training_checkpoint(version) == version / CHECKPOINT_FILE
    assert sha256_file(version / CHECKPOINT_FILE) == manifest.training.checkpoint_sha256
    assert CHECKPOINT_FILE not in manifest.files  # servers neither read nor verify it

    copy = Path(shutil.copytree(version, tmp_path / "000001"))
    (copy / CHECKPOINT_FILE).write_bytes(b"not the checkpoint")
    with pytest.raises(RepositoryError, match="does not match the SHA-256 in its manifest"):
        training_checkpoint(copy)
    (copy / CHECKPOINT_FILE).unlink()
    with pytest.raises(RepositoryError, match="training checkpoint is missing"):
        training_checkpoint(copy)
    referenced = dataclasses.replace(
        manifest, training=dataclasses.replace(manifest.training, checkpoint_file=None)
    )
    assert training_checkpoint(copy, referenced) == Path(manifest.training.checkpoint)
