import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from detmatch.data.dataset import collate, make_sample
from detmatch.data.kitti import KittiDataset
from detmatch.inference import predict_batch
from detmatch.matching_policy import MatchingPolicy
from detmatch.models.build import load_detectors
from detmatch.pseudo_labels import MatchedLabels, Provenance, match_detections
from export.parity import Tolerance, check_parity
from serving.labeler import Frame, Labeler, Overrides
from serving.repository import MODEL_3D_FILE, RepositoryError
from serving.sessions import SessionSettings
from tests.conftest import KITTI_SAMPLE, REPO


def _frames(synth_root):
    for root in (synth_root, KITTI_SAMPLE):
        dataset = KittiDataset(root)
        for frame_id in dataset.ids():
            yield dataset.load_frame(frame_id, with_labels=False)


def _rows(labels: MatchedLabels) -> list[np.ndarray]:
    return [
        np.array([labels.provenance[i], labels.class_3d[i], labels.class_2d[i],
                  *labels.boxes_3d[i], *labels.boxes_2d[i], labels.score_3d[i],
                  labels.score_2d[i], labels.cost[i]], dtype=np.float64)
        for i in range(len(labels))
    ]  # fmt: skip


def assert_same_labels(got: MatchedLabels, expected: MatchedLabels, atol: float = 1e-3) -> None:
    """Same rows (row order follows detection order, which top-k ties may permute): each
    expected row pairs with a distinct row of equal provenance and classes whose boxes,
    scores and cost are within atol."""
    got_rows, expected_rows = _rows(got), _rows(expected)
    assert len(got_rows) == len(expected_rows)
    unused = list(range(len(got_rows)))
    for row in expected_rows:
        candidates = [g for g in unused if (got_rows[g][:3] == row[:3]).all()]
        assert candidates, f"no label like {row}"
        best = min(candidates, key=lambda g: np.nanmax(np.abs(got_rows[g][3:] - row[3:])))
        np.testing.assert_allclose(got_rows[best][3:], row[3:], atol=atol, rtol=0, equal_nan=True)
        unused.remove(best)


# Default thresholds, and a permissive matching threshold: the 6-step tiny model's detections
# are too poor to match at tau_hung = -1.5, so the second case is what exercises matching.
@pytest.mark.parametrize(
    "overrides",
    [{}, {"tau_hung": 50.0, "tau_3d_outside_view": 0.1}, {"tau_3d_unmatched": 0.1}],
    ids=["manifest", "permissive", "lidar-only-in-view"],
)
def test_labels_equal_the_pytorch_pipeline(
    exported_repository, trained_checkpoint, synth_root, overrides
):
    """On every frame where both give the same detections, the labeler's labels are the
    PyTorch pipeline's (predict_batch, then match_detections). The barely trained model's
    heatmaps are nearly flat, so float rounding can swap which of two near-tied peaks is
    detected; such frames must pass the export's parity check (the difference is an excused
    near tie), and they are counted, not compared."""
    loaded = load_detectors(trained_checkpoint)
    config, model_2d, model_3d = loaded.config, loaded.model_2d, loaded.model_3d
    labeler = Labeler.from_repository(exported_repository)
    grid = model_3d.grid
    # The manifest's policy is the training config's (LiDAR-only labels above 0.6 by default).
    assert labeler.policy == MatchingPolicy.from_config(config.ssl)
    assert labeler.tau_3d_unmatched == config.ssl.tau_3d_unmatched == 0.6
    policy = MatchingPolicy(
        tau_hung=overrides.get("tau_hung", -1.5),
        tau_3d_outside_view=overrides.get("tau_3d_outside_view", 0.3),
        tau_3d_unmatched=overrides.get("tau_3d_unmatched", 0.6),
    )
    provenances, tie_affected = [], []
    for frame in _frames(synth_root):
        sample = make_sample(frame, config.data.classes, config.data.image_size, grid, flip=False)
        detections_2d, detections_3d = predict_batch(model_2d, model_3d, collate([sample]))[0]
        expected = match_detections(detections_3d, detections_2d, frame.calib, frame.image_size,
                                    policy)  # fmt: skip
        result = labeler.label(frame.image, frame.points, frame.calib, **overrides)
        parity = check_parity(labeler.session_2d, labeler.session_3d, model_2d, model_3d, config,
                              [("frame", frame)], Tolerance())  # fmt: skip
        assert parity.passed, parity.summary()
        (frame_parity,) = parity.frames
        if sum(frame_parity.unpaired_at_cut.values()) + sum(frame_parity.unpaired_at_peak.values()):
            tie_affected.append(frame.frame_id)
            continue
        assert len(result.detections_2d) == len(detections_2d)
        assert len(result.detections_3d) == len(detections_3d)
        assert_same_labels(result.labels, expected)
        provenances.extend(result.labels.provenance.tolist())
    assert len(tie_affected) <= 2, tie_affected
    if "tau_hung" in overrides:
        assert Provenance.MATCHED in provenances
        assert Provenance.LIDAR_ONLY_OUTSIDE_VIEW in provenances
    if "tau_3d_unmatched" in overrides:  # low enough for the barely trained model's scores
        assert Provenance.LIDAR_ONLY_CONFIDENT in provenances


def test_label_reports_version_thresholds_and_timings(exported_repository, synth_root):
    labeler = Labeler.from_repository(exported_repository, version=1)
    frame = KittiDataset(synth_root).load_frame("000000")
    result = labeler.label(frame.image, frame.points, frame.calib, tau_hung=50.0,
                           score_threshold_2d=0.2, outside_view_fallback=False)  # fmt: skip
    assert result.model_version == "000001"
    assert result.classes == ("Car", "Pedestrian", "Cyclist")
    assert result.thresholds == {
        "tau_hung": 50.0,
        "score_threshold_2d": 0.2,
        "score_threshold_3d": 0.1,
        "tau_3d_outside_view": None,
        "tau_3d_unmatched": 0.6,  # the manifest's: the training default
    }
    assert (result.detections_2d.scores > 0.2).all()
    assert Provenance.LIDAR_ONLY_OUTSIDE_VIEW not in result.labels.provenance
    assert set(result.timings) == {"detector2d", "pillarize", "detector3d", "matching", "total"}
    assert result.timings["total"] >= sum(v for k, v in result.timings.items() if k != "total")
    assert len(result.names) == len(result)


def test_empty_and_out_of_range_point_clouds_give_the_same_labels(exported_repository, synth_root):
    labeler = Labeler.from_repository(exported_repository)
    frame = KittiDataset(synth_root).load_frame("000000")
    empty = labeler.label(frame.image, np.zeros((0, 4), np.float32), frame.calib)
    far = labeler.label(frame.image, np.full((5, 4), 500.0, np.float32), frame.calib)
    np.testing.assert_array_equal(empty.detections_3d.boxes, far.detections_3d.boxes)
    labeler.warm_up()


def test_malformed_inputs_raise_value_errors_naming_the_field(exported_repository, synth_root):
    labeler = Labeler.from_repository(exported_repository)
    frame = KittiDataset(synth_root).load_frame("000000")
    image, points, calib = frame.image, frame.points, frame.calib
    bad_points = points.copy()
    bad_points[3, 1] = np.nan
    cases = [
        ((image.astype(np.float32), points, calib), {}, "image: expected dtype uint8"),
        ((image[..., :2], points, calib), {}, r"image: expected shape \(H, W, 3\)"),
        ((image[:0], points, calib), {}, "image: empty"),
        ((image, points[:, :3], calib), {}, r"points: expected shape \(N, 4\)"),
        ((image, points.astype(np.float64), calib), {}, "points: expected dtype float32"),
        ((image, bad_points, calib), {}, "points: 1 points hold NaN or Inf"),
        ((image, points, "P2"), {}, "calib: expected a Calibration"),
        ((image, points, calib), {"score_threshold_2d": 1.5}, "score_threshold_2d"),
        ((image, points, calib), {"tau_hung": float("nan")}, "tau_hung: expected a finite"),
    ]
    for args, kwargs, message in cases:
        with pytest.raises(ValueError, match=message):
            labeler.label(*args, **kwargs)


def test_a_batch_gives_each_frame_the_labels_it_gets_alone(exported_repository, synth_root):
    """Frames of several image sizes (the synthetic and the KITTI samples), one with an empty
    point cloud and per-frame options, labeled in one `label_batch`: each frame's labels and
    detections are those `label` gives it alone."""
    labeler = Labeler.from_repository(exported_repository)
    frames = [Frame(f.image, f.points, f.calib) for f in _frames(synth_root)]
    frames[1] = Frame(frames[1].image, np.zeros((0, 4), np.float32), frames[1].calib)
    frames[2] = Frame(frames[2].image, frames[2].points, frames[2].calib,
                      Overrides(tau_hung=50.0, tau_3d_outside_view=0.1))  # fmt: skip
    assert len({f.image.shape for f in frames}) >= 2 and len(frames) >= 4
    batched = labeler.label_batch(frames)
    for frame, got in zip(frames, batched, strict=True):
        alone = labeler.label(frame.image, frame.points, frame.calib,
                              tau_hung=frame.options.tau_hung,
                              tau_3d_outside_view=frame.options.tau_3d_outside_view)  # fmt: skip
        assert got.batch_size == len(frames) and alone.batch_size == 1
        assert got.thresholds == alone.thresholds
        assert_same_labels(got.labels, alone.labels)
        for mine, theirs in ((got.detections_2d, alone.detections_2d),
                             (got.detections_3d, alone.detections_3d)):  # fmt: skip
            assert len(mine) == len(theirs)
            np.testing.assert_allclose(np.sort(mine.scores), np.sort(theirs.scores), atol=1e-4)
    assert len(batched[2].labels) > 0  # the permissive frame matched something


def test_a_bad_frame_in_a_batch_fails_only_itself(exported_repository, synth_root):
    labeler = Labeler.from_repository(exported_repository)
    good = [Frame(f.image, f.points, f.calib) for f in _frames(synth_root)][:3]
    nan_points = good[0].points.copy()
    nan_points[0, 2] = np.nan
    batch = [
        good[0],
        Frame(good[1].image, nan_points, good[1].calib),
        good[1],
        Frame(good[2].image, good[2].points, good[2].calib, Overrides(score_threshold_2d=2.0)),
        good[2],
    ]
    results = labeler.label_batch(batch)
    assert isinstance(results[1], ValueError) and "points: 1 points hold NaN" in str(results[1])
    assert isinstance(results[3], ValueError) and "score_threshold_2d" in str(results[3])
    for i, frame in ((0, good[0]), (2, good[1]), (4, good[2])):
        assert results[i].batch_size == 3
        alone = labeler.label(frame.image, frame.points, frame.calib)
        assert_same_labels(results[i].labels, alone.labels)
    only_bad = labeler.label_batch([batch[1], batch[3]])
    assert [type(r) for r in only_bad] == [ValueError, ValueError]


def test_a_corrupted_or_missing_version_is_refused(exported_repository, tmp_path):
    repository = tmp_path / "models"
    shutil.copytree(exported_repository, repository)
    with open(repository / "000001" / MODEL_3D_FILE, "r+b") as handle:
        handle.seek(-10, os.SEEK_END)
        handle.write(b"0123456789")
    with pytest.raises(RepositoryError, match="does not match its checksum"):
        Labeler.from_repository(repository)
    with pytest.raises(FileNotFoundError, match="no version 000002"):
        Labeler.from_repository(repository, version=2)
    (repository / "000001" / "PROMOTED").unlink()
    with pytest.raises(FileNotFoundError, match="no promoted version"):
        Labeler.from_repository(repository)


def test_a_version_exported_before_the_batch_axis_is_refused_with_the_fix(
    exported_repository, tmp_path
):
    """A 2D graph of the old contract (one (H, W, 3) image, no batch axis): the labeler names
    the command that exports the version's checkpoint again."""
    import onnx
    from onnx import TensorProto, helper

    outputs = [
        ("boxes", TensorProto.FLOAT, [30, 4]),
        ("scores", TensorProto.FLOAT, [30]),
        ("classes", TensorProto.INT64, [30]),
        ("probabilities", TensorProto.FLOAT, [30, 3]),
    ]
    graph = helper.make_graph(
        [
            helper.make_node(
                "Constant",
                [],
                [name],
                value=helper.make_tensor(
                    name + "_value", dtype, shape, np.zeros(shape).ravel().tolist()
                ),
            )
            for name, dtype, shape in outputs
        ],  # fmt: skip
        "legacy",
        [helper.make_tensor_value_info("image", TensorProto.UINT8, ["height", "width", 3])],
        [helper.make_tensor_value_info(name, dtype, shape) for name, dtype, shape in outputs],
    )
    version = tmp_path / "models" / "000001"
    shutil.copytree(exported_repository / "000001", version)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(version / "detector2d.onnx"))
    with pytest.raises(RepositoryError, match="without a leading batch axis") as refused:
        Labeler(version, check_files=False)
    assert f"--checkpoint {version / 'checkpoint.pt'}" in str(refused.value)


def test_the_labeler_runs_where_torch_cannot_be_imported(exported_repository, synth_root, tmp_path):
    """serving imports no torch anywhere on its import path: a process where `import torch`
    fails loads the served version, labels a real KITTI frame and runs `detmatch label`."""
    script = textwrap.dedent(
        f"""
        import sys
        sys.modules["torch"] = None  # any `import torch` now raises ImportError
        import serving, serving.repository, serving.sessions, serving.labeler, serving.offline
        from detmatch.data.kitti import KittiDataset
        from serving.labeler import Labeler

        frame = KittiDataset({str(KITTI_SAMPLE)!r}).load_frame("000000", with_labels=False)
        labeler = Labeler.from_repository({str(exported_repository)!r},
                                          settings=serving.sessions.SessionSettings(1))
        result = labeler.label(frame.image, frame.points, frame.calib, tau_hung=50.0)
        from commands.main import main
        assert main(["label", "--repository", {str(exported_repository)!r},
                     "--data", {str(synth_root)!r}, "--split", "val",
                     "--out", {str(tmp_path / "labels")!r}]) == 0
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "onnx"))
        print("labels", len(result), "version", result.model_version, "loaded", loaded)
        """
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=REPO, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "version 000001" in done.stdout
    assert done.stdout.strip().endswith("loaded ['torch']")  # only the blocking None entry
    assert int(done.stdout.split()[1]) > 0


def test_session_settings_are_validated():
    assert SessionSettings().threads >= 1
    assert SessionSettings(intra_op_threads=3).threads == 3
    with pytest.raises(ValueError, match="graph_optimization"):
        SessionSettings(graph_optimization="max")
    with pytest.raises(ValueError, match="intra_op_threads"):
        SessionSettings(intra_op_threads=-1)


def test_threads_follow_the_cgroup_cpu_quota(tmp_path):
    """A container's CPU limit (cgroup v2 cpu.max, v1 cfs quota) caps onnxruntime's threads;
    the CPU set alone does not show it."""
    from serving.sessions import cgroup_cpu_limit

    v2 = tmp_path / "v2"
    (v2 / "kubepods" / "pod1").mkdir(parents=True)
    (v2 / "kubepods" / "cpu.max").write_text("max 100000\n")
    (v2 / "kubepods" / "pod1" / "cpu.max").write_text("150000 100000\n")
    proc = tmp_path / "cgroup_v2"
    proc.write_text("0::/kubepods/pod1\n")
    assert cgroup_cpu_limit(proc, v2) == 1.5
    (v2 / "kubepods" / "cpu.max").write_text("50000 100000\n")  # a stricter parent
    assert cgroup_cpu_limit(proc, v2) == 0.5
    v1 = tmp_path / "v1"
    (v1 / "cpu,cpuacct" / "docker" / "abc").mkdir(parents=True)
    (v1 / "cpu,cpuacct" / "docker" / "abc" / "cpu.cfs_quota_us").write_text("200000\n")
    (v1 / "cpu,cpuacct" / "docker" / "abc" / "cpu.cfs_period_us").write_text("100000\n")
    proc_v1 = tmp_path / "cgroup_v1"
    proc_v1.write_text("5:cpu,cpuacct:/docker/abc\n4:memory:/docker/abc\n")
    assert cgroup_cpu_limit(proc_v1, v1) == 2.0
    unlimited = tmp_path / "unlimited"
    unlimited.mkdir()
    (unlimited / "cpu.max").write_text("max 100000\n")
    (tmp_path / "cgroup_root").write_text("0::/\n")
    assert cgroup_cpu_limit(tmp_path / "cgroup_root", unlimited) is None
    assert cgroup_cpu_limit(tmp_path / "missing", unlimited) is None


def test_sessions_run_without_the_memory_arena(exported_repository):
    """onnxruntime's arena kept whatever one large input needed (+1.2 GB for good)."""
    labeler = Labeler.from_repository(exported_repository)
    for session in (labeler.session_2d, labeler.session_3d):
        assert session.get_session_options().enable_cpu_mem_arena is False
