import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from commands.main import main
from detmatch.data.kitti import KittiFormatError, KittiObjects, read_objects, write_objects
from detmatch.eval.kitti import evaluate, evaluate_dirs, format_table
from tests.eval.helpers import noisy_detections, random_scene

CLASSES = ["Car", "Pedestrian", "Cyclist"]
SAMPLE_IDS = ["000000", "000001", "000002"]


def write_set(root: Path, gt, dt, ids: list[str]) -> tuple[Path, Path, Path]:
    """Label files, result files and an ids file under root."""
    for frame_id, labels, results in zip(ids, gt, dt, strict=True):
        write_objects(root / "label_2" / f"{frame_id}.txt", labels)
        write_objects(root / "results" / f"{frame_id}.txt", results)
    ids_file = root / "ids.txt"
    ids_file.write_text("".join(f"{i}\n" for i in ids))
    return root / "label_2", root / "results", ids_file


@pytest.fixture()
def small_set(tmp_path):
    rng = np.random.default_rng(7)
    gt = random_scene(rng, 25)
    dt = noisy_detections(rng, gt)
    ids = [f"{i:06d}" for i in range(len(gt))]
    return (*write_set(tmp_path, gt, dt, ids), ids)


def assert_exact_shape(results: dict, classes: list[str], metrics: list[str]) -> None:
    assert list(results) == classes
    for per_class in results.values():
        assert list(per_class) == ["R40", "R11"]
        for table in per_class.values():
            assert list(table) == metrics
            for values in table.values():
                assert len(values) == 3
                assert all(isinstance(v, float) and 0.0 <= v <= 100.0 for v in values)


def test_cli_prints_a_table_and_writes_json_of_the_exact_shape(small_set, tmp_path, capsys):
    gt_dir, pred_dir, ids_file, ids = small_set
    out = tmp_path / "out" / "eval.json"
    argv = ["eval", "--gt-dir", str(gt_dir), "--pred-dir", str(pred_dir),
            "--ids-file", str(ids_file), "--classes", "Car,Pedestrian,Cyclist",
            "--json", str(out)]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out
    results = json.loads(out.read_text())
    assert_exact_shape(results, CLASSES, ["bbox", "bev", "3d", "aos"])
    assert results == json.loads(json.dumps(evaluate_dirs(gt_dir, pred_dir, ids, CLASSES)))
    assert printed.strip() == format_table(results)
    assert "Pedestrian" in printed and "moderate" in printed
    assert f"{results['Car']['R40']['3d'][1]:.2f}" in printed


def test_installed_command_runs(small_set, tmp_path):
    gt_dir, pred_dir, ids_file, _ = small_set
    command = shutil.which("detmatch") or str(Path(sys.executable).parent / "detmatch")
    out = tmp_path / "eval.json"
    done = subprocess.run(
        [command, "eval", "--gt-dir", str(gt_dir), "--pred-dir", str(pred_dir),
         "--ids-file", str(ids_file), "--classes", "Car,Pedestrian,Cyclist", "--json", str(out)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert_exact_shape(json.loads(out.read_text()), CLASSES, ["bbox", "bev", "3d", "aos"])
    assert "R40" in done.stdout


def test_missing_result_file_means_no_detections(small_set):
    gt_dir, pred_dir, _, ids = small_set
    gt = [read_objects(gt_dir / f"{i}.txt") for i in ids]
    dt = [read_objects(pred_dir / f"{i}.txt") for i in ids]
    dt[4] = KittiObjects.empty(with_score=True)
    (pred_dir / f"{ids[4]}.txt").unlink()
    assert evaluate_dirs(gt_dir, pred_dir, ids, CLASSES) == evaluate(gt, dt, CLASSES)
    # A folder without any of the frames' result files is a mistake (the wrong folder, or the
    # parent of `detmatch predict`'s 3d/ and 2d/), not a model that detected nothing.
    for path in pred_dir.iterdir():
        path.unlink()
    (pred_dir / "3d").mkdir()
    with pytest.raises(ValueError, match=r"no result file for any of the \d+ frames.*3d"):
        evaluate_dirs(gt_dir, pred_dir, ids, CLASSES)


def test_file_errors_are_clear(small_set, capsys):
    gt_dir, pred_dir, ids_file, ids = small_set
    (gt_dir / f"{ids[2]}.txt").unlink()
    with pytest.raises(FileNotFoundError, match=f"{ids[2]}.txt"):
        evaluate_dirs(gt_dir, pred_dir, ids, CLASSES)
    argv = ["eval", "--gt-dir", str(gt_dir), "--pred-dir", str(pred_dir),
            "--ids-file", str(ids_file)]  # fmt: skip
    assert main(argv) == 2
    assert "no ground-truth label file" in capsys.readouterr().err

    ids = ids[3:]
    broken = pred_dir / f"{ids[0]}.txt"
    lines = broken.read_text().splitlines()
    broken.write_text("\n".join([*lines[:1], "Car 0 0 0 1 2 3 oops 1 1 1 1 1 1 1 0.5", *lines[1:]]))
    with pytest.raises(KittiFormatError) as error:
        evaluate_dirs(gt_dir, pred_dir, ids, CLASSES)
    assert error.value.path == str(broken) and error.value.line == 2

    unscored = pred_dir / f"{ids[0]}.txt"
    unscored.write_text("Car 0.00 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.6 20.0 0.1\n")
    with pytest.raises(KittiFormatError, match="16 fields"):
        evaluate_dirs(gt_dir, pred_dir, ids, CLASSES)
    with pytest.raises(ValueError, match="unknown KITTI class"):
        evaluate_dirs(gt_dir, pred_dir, ids, ["Car", "Bus"])
    with pytest.raises(FileNotFoundError, match="result directory"):
        evaluate_dirs(gt_dir, pred_dir / "nope", ids, CLASSES)


def test_two_d_only_result_files(tmp_path):
    rng = np.random.default_rng(11)
    gt = random_scene(rng, 20)
    dt = noisy_detections(rng, gt)
    ids = [f"{i:06d}" for i in range(len(gt))]
    gt_dir, pred_dir, ids_file = write_set(tmp_path, gt, dt, ids)
    for path in pred_dir.iterdir():
        # Keep type, box and score; KITTI's placeholders for everything 3D (and alpha).
        lines = []
        for line in path.read_text().splitlines():
            f = line.split()
            lines.append(" ".join([f[0], "-1", "-1", "-10", *f[4:8], "-1 -1 -1",
                                   "-1000 -1000 -1000", "-10", f[15]]))  # fmt: skip
        path.write_text("".join(f"{line}\n" for line in lines))
    out = tmp_path / "eval.json"
    argv = ["eval", "--gt-dir", str(gt_dir), "--pred-dir", str(pred_dir),
            "--ids-file", str(ids_file), "--json", str(out)]  # fmt: skip
    assert main(argv) == 0
    results = json.loads(out.read_text())
    assert_exact_shape(results, CLASSES, ["bbox"])
    assert any(v > 0 for c in results.values() for v in c["R11"]["bbox"])


def _gt_as_results(label_dir: Path, result_dir: Path, copies: int) -> list[str]:
    """Label files copied `copies` times under new ids, with a score column: GT as results
    (DontCare rows left out: a detector does not report them, and their alpha is -10)."""
    ids = []
    for copy in range(copies):
        for sample_id in SAMPLE_IDS:
            frame_id = f"{copy:03d}{sample_id[3:]}"
            text = (label_dir / f"{sample_id}.txt").read_text()
            (result_dir.parent / "label_2").mkdir(exist_ok=True)
            (result_dir.parent / "label_2" / f"{frame_id}.txt").write_text(text)
            score = f"{0.5 + copy / (2 * copies):.4f}"
            scored = [f"{line} {score}" for line in text.splitlines() if "DontCare" not in line]
            (result_dir / f"{frame_id}.txt").write_text("\n".join(scored) + "\n")
            ids.append(frame_id)
    return ids


def test_real_kitti_labels_as_predictions(kitti_sample, tmp_path):
    label_dir = kitti_sample / "training" / "label_2"
    results_dir = tmp_path / "results"
    results_dir.mkdir()
    ids = _gt_as_results(label_dir, results_dir, copies=1)
    three = evaluate_dirs(tmp_path / "label_2", results_dir, ids, CLASSES)
    # One valid Pedestrian (every difficulty) and one moderate/hard Car: the sample-count
    # effect leaves a single recall point, 0 of the 40 (R40) and 1 of the 11 (R11).
    for metric in ("bbox", "bev", "3d", "aos"):
        assert three["Pedestrian"]["R40"][metric] == [0.0, 0.0, 0.0]
        np.testing.assert_allclose(three["Pedestrian"]["R11"][metric], [100 / 11] * 3)
        np.testing.assert_allclose(three["Car"]["R11"][metric], [0.0, 100 / 11, 100 / 11])
        assert three["Cyclist"]["R11"][metric] == [0.0, 0.0, 0.0]  # occluded 3: never valid

    # 45 copies: 45 valid Pedestrians and Cars -> 100 wherever the ground truth has objects.
    many_dir = tmp_path / "many" / "results"
    many_dir.mkdir(parents=True)
    ids = _gt_as_results(label_dir, many_dir, copies=45)
    many = evaluate_dirs(tmp_path / "many" / "label_2", many_dir, ids, CLASSES)
    for recall in ("R40", "R11"):
        for metric in ("bbox", "bev", "3d", "aos"):
            np.testing.assert_allclose(many["Pedestrian"][recall][metric], [100.0] * 3)
            # No Car is easy (heights 22 and 33 px): 0 there, as in the official code.
            np.testing.assert_allclose(many["Car"][recall][metric], [0.0, 100.0, 100.0])
            assert many["Cyclist"][recall][metric] == [0.0, 0.0, 0.0]
