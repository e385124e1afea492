"""Commands that write a directory refuse a non-empty one unless --overwrite (which first
removes what the command writes there), and answer a user's mistake with one line and exit 2."""

import pytest

from commands.main import main
from detmatch.data.kitti import KittiDataset, read_image_set


def test_synth_refuses_an_existing_data_set_and_overwrite_leaves_no_old_frame(tmp_path, capsys):
    out = tmp_path / "synth"
    argv = ["synth", "--out", str(out), "--seed", "0", "--quiet"]
    assert main([*argv, "--frames", "4"]) == 0
    capsys.readouterr()
    assert main([*argv, "--frames", "2"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "--overwrite" in error and str(out) in error
    assert len(KittiDataset(out).ids("trainval")) == 4  # untouched
    (out / "notes.txt").write_text("mine")
    assert main([*argv, "--frames", "2", "--overwrite"]) == 0
    assert sorted(p.stem for p in (out / "training" / "image_2").iterdir()) == [
        "000000",
        "000001",
    ]
    assert read_image_set(out / "ImageSets" / "trainval.txt") == ["000000", "000001"]
    assert (out / "notes.txt").read_text() == "mine"  # not something synth writes


@pytest.mark.parametrize(
    "argv",
    [
        ["store", "export", "--store", "STORE"],
        ["predict", "--checkpoint", "RUN", "--data", "DATA", "--all"],
        ["label", "--repository", "REPO", "--data", "DATA", "--all"],
    ],
)
def test_commands_refuse_a_non_empty_out(tmp_path, capsys, argv):
    out = tmp_path / "out"
    out.mkdir()
    (out / "earlier.txt").write_text("an earlier result")
    argv = [str(tmp_path / a.lower()) if a.isupper() else a for a in argv]
    assert main([*argv, "--out", str(out)]) == 2
    assert "is not empty: pass --overwrite" in capsys.readouterr().err
    assert (out / "earlier.txt").read_text() == "an earlier result"


def test_store_export_of_a_missing_store_is_an_error(tmp_path, capsys):
    argv = ["store", "export", "--store", str(tmp_path / "nosuch"), "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    assert "no label store at" in capsys.readouterr().err


def test_label_blames_a_bad_namespace_not_the_frame_id(tmp_path, capsys):
    argv = ["label", "--repository", str(tmp_path), "--data", str(tmp_path), "--all",
            "--store", str(tmp_path / "store"), "--namespace", "a b"]  # fmt: skip
    assert main(argv) == 2
    error = capsys.readouterr().err
    assert "invalid namespace 'a b'" in error and "frame id" not in error


def test_show_reads_the_3d_folder_that_predict_and_label_write(kitti_sample, tmp_path, capsys):
    predictions = tmp_path / "labels"
    (predictions / "3d").mkdir(parents=True)
    label = (kitti_sample / "training" / "label_2" / "000002.txt").read_text().splitlines()[1]
    (predictions / "3d" / "000002.txt").write_text(label + " 0.87\n")
    out = tmp_path / "frame.png"
    argv = ["show", "--data", str(kitti_sample), "--frame", "000002", "--out", str(out)]
    assert main([*argv, "--predictions", str(predictions)]) == 0
    assert out.stat().st_size > 0
    assert main([*argv, "--predictions", str(predictions / "3d"), "--frame", "000001"]) == 2
    assert "no result file for frame 000001" in capsys.readouterr().err


def test_health_refuses_a_target_that_is_not_host_and_port(capsys):
    assert main(["health", "--target", "nonsense", "--wait-s", "0"]) == 2
    assert "expected HOST:PORT" in capsys.readouterr().err


def test_health_says_why_a_target_is_unreachable(capsys):
    assert main(["health", "--target", "127.0.0.1:1", "--wait-s", "0"]) == 1
    captured = capsys.readouterr()
    assert captured.out == "UNREACHABLE\n"
    assert "no gRPC server answered at 127.0.0.1:1" in captured.err


def test_train_ends_saying_where_the_checkpoint_is(synth_root, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["train", "--config", "tiny", "--data", str(synth_root), "--out", str(out),
            "--set", "train.steps=2", "--set", "train.eval_every=2"]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    assert printed[0] == f"trained {out} to step 2"
    assert printed[1].startswith("mAP (moderate, R40) on 'val': 3D ")
    assert printed[2] == f"checkpoint: {out / 'checkpoints' / 'step_00000002.pt'}"
    assert (out / "checkpoints" / "step_00000002.pt").is_file()
    assert len(printed) == 4


def test_serve_refuses_a_missing_repository_or_tls_file_before_creating_the_store(tmp_path, capsys):
    store = tmp_path / "store"
    base = ["serve", "--store", str(store), "--no-auth", "--port", "0"]
    assert main([*base, "--repository", str(tmp_path / "nosuch")]) == 2
    assert "--repository" in capsys.readouterr().err
    (tmp_path / "models").mkdir()
    tls = ["--tls-cert", str(tmp_path / "cert.pem"), "--tls-key", str(tmp_path / "key.pem")]
    assert main([*base, "--repository", str(tmp_path / "models"), *tls]) == 2
    assert "--tls-cert" in capsys.readouterr().err
    assert not store.exists()
