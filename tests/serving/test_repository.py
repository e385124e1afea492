import json
import os

import pytest

from serving.manifest import Manifest, ManifestError
from serving.repository import (
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
    data["matching"]["tau_3d_outside_view"] = 1.5
    with pytest.raises(ManifestError, match=r"matching: tau_3d_outside_view must be in \[0, 1\)"):
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
