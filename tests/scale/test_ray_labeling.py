"""`detmatch label --engine ray` (serving.ray_labeling) on a real local Ray instance: the same
files and stored frames as `label_split`, resume, a corrupt frame, a killed actor, and the
errors that name what to do. Every Ray run is bounded by TIMEOUT_S (a pipeline that cannot get
a CPU waits for ever rather than failing)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

if os.environ.get("DETMATCH_REQUIRE_RAY"):  # .ci/run installs the ray extra: never skip there
    import ray
    import ray.data
else:
    ray = pytest.importorskip("ray", reason="the ray extra: pip install -e '.[ray]'")
    pytest.importorskip("ray.data")

from commands.main import main  # noqa: E402
from detmatch.data.selection import FrameSelection  # noqa: E402
from detmatch.data.synth import generate_dataset  # noqa: E402
from serving.labeler import Labeler  # noqa: E402
from serving.offline import label_split  # noqa: E402
from serving.ray_labeling import (  # noqa: E402
    CRASH_ONCE_ENV,
    RayEngine,
    RayEngineError,
    label_with_ray,
)
from serving.store import LabelStore  # noqa: E402
from tests.conftest import REPO  # noqa: E402
from tests.onnx_fixtures import exported_repository  # noqa: E402, F401
from tests.stock_kitti import make_stock_kitti  # noqa: E402

TIMEOUT_S = 120
TAU_HUNG = 50.0  # the tiny model's costs are high: with the manifest's threshold few labels
ALL = FrameSelection(all_frames=True)
RESULT_DIRS = ("3d", "2d", "labels")
SMALL = RayEngine(actors=2, batch_size=2)


def bounded(function, *args, **kwargs):
    """function(*args, **kwargs) in a thread; fails the test after TIMEOUT_S. (The function
    may use Ray, not start it: see `alarm`.)"""
    outcome: dict = {}

    def run() -> None:
        try:
            outcome["value"] = function(*args, **kwargs)
        except BaseException as error:  # noqa: BLE001 - re-raised in the test's thread
            outcome["error"] = error

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(TIMEOUT_S)
    if thread.is_alive():
        pytest.fail(f"{function.__name__} did not finish within {TIMEOUT_S} s")
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


@contextlib.contextmanager
def alarm(seconds: int) -> Iterator[None]:
    """TimeoutError in this (the main) thread after `seconds`: Ray must start and stop in the
    main thread (its processes die with the thread that started them)."""

    def expire(signum, frame):
        raise TimeoutError(f"Ray did not start or stop within {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture(scope="module", autouse=True)
def local_ray(tmp_path_factory):
    """One local Ray instance for the module: 2 CPUs on loopback, no dashboard."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RAY_USAGE_STATS_ENABLED", "0")
        patch.setenv("RAY_AUTH_MODE", "disabled")
        patch.delenv("RAY_ADDRESS", raising=False)
        with alarm(TIMEOUT_S):
            ray.init(
                num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1",
                _temp_dir=str(tmp_path_factory.mktemp("ray")), log_to_driver=False,
            )  # fmt: skip
        try:
            yield
        finally:
            with alarm(TIMEOUT_S):
                ray.shutdown()


@pytest.fixture(scope="module")
def synth_set(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ray_synth")
    generate_dataset(root, 8, seed=0, progress=False)
    return root


@pytest.fixture(scope="module")
def labeler(exported_repository) -> Labeler:  # noqa: F811
    return Labeler.from_repository(exported_repository)


def result_files(out: Path) -> dict[str, bytes]:
    return {
        f"{kind}/{path.name}": path.read_bytes()
        for kind in RESULT_DIRS
        for path in sorted((out / kind).iterdir())
    }


def same_summary(ray_summary, split_summary) -> None:
    assert {**ray_summary.__dict__, "seconds": 0} == {**split_summary.__dict__, "seconds": 0}


@pytest.mark.parametrize("source", ["path", "file_url"])
def test_ray_writes_the_files_label_split_writes(
    exported_repository,  # noqa: F811
    labeler,
    kitti_sample,
    synth_set,
    tmp_path,
    source,
):
    """The KITTI sample and a synthetic set, read from a directory or a file:// URL: byte-for-
    byte label_split's files, the same summary, labeling.json with the engine's fields."""
    for name, data in (("kitti", kitti_sample), ("synth", synth_set)):
        expected = label_split(labeler, data, ALL, tmp_path / f"{name}_split", TAU_HUNG,
                               progress=False)  # fmt: skip
        where = str(data) if source == "path" else data.resolve().as_uri()
        got = bounded(label_with_ray, exported_repository, where, ALL, tmp_path / f"{name}_ray",
                      tau_hung=TAU_HUNG, progress=False, engine=SMALL)  # fmt: skip
        assert got.resumed == 0 and got.failed == ()
        same_summary(got.summary, expected)
        files = result_files(tmp_path / f"{name}_ray")
        assert files == result_files(tmp_path / f"{name}_split")
        assert len(files) == 3 * expected.frames
        record = json.loads((tmp_path / f"{name}_ray" / "labeling.json").read_text())
        split_record = json.loads((tmp_path / f"{name}_split" / "labeling.json").read_text())
        for key in ("frames", "labels", "matched", "model_version", "model_path", "subset",
                    "frames_selected", "thresholds"):  # fmt: skip
            assert record[key] == split_record[key], key
        assert record["data"] == (split_record["data"] if source == "path" else where)
        assert record["engine"]["name"] == "ray" and record["engine"]["actors"] == 2
        assert record["resumed"] == 0 and record["failed"] == []
    assert expected.labels > 0


def test_the_store_holds_what_label_split_stores_and_a_rerun_resumes(
    exported_repository,  # noqa: F811
    labeler,
    kitti_sample,
    tmp_path,
):
    """A stock KITTI layout (a JPEG frame, stored as PNG) from a file:// URL into a label
    store: every stored frame has label_split's files; labeling again skips every frame, and a
    frame whose labels file is gone is labeled again, alone."""
    stock = make_stock_kitti(kitti_sample, tmp_path / "kitti")
    with LabelStore(tmp_path / "split_store", "offline") as store:
        expected = label_split(labeler, stock, ALL, None, TAU_HUNG, progress=False, store=store)
        expected_records = {i: store.get(i) for i in ("000000", "000001", "000002")}
    out = tmp_path / "out"
    with LabelStore(tmp_path / "ray_store", "offline") as store:
        got = bounded(label_with_ray, exported_repository, stock.as_uri(), ALL, out,
                      tau_hung=TAU_HUNG, progress=False, store=store, engine=SMALL)  # fmt: skip
        same_summary(got.summary, expected)
        for frame_id, wanted in expected_records.items():
            record = store.get(frame_id)
            for field in ("model_version", "num_labels", "num_matched", "num_lidar_only",
                          "provenance", "files"):  # fmt: skip
                assert getattr(record, field) == getattr(wanted, field), (frame_id, field)

        again = bounded(label_with_ray, exported_repository, stock, ALL, out, tau_hung=TAU_HUNG,
                        progress=False, store=store, engine=SMALL)  # fmt: skip
        assert again.resumed == 3 and again.summary.frames == 0
        assert again.summary.stored == 0 and again.summary.already_stored == 3

        (out / "labels" / "000001.json").unlink()
        one = bounded(label_with_ray, exported_repository, stock, ALL, out, tau_hung=TAU_HUNG,
                      progress=False, store=store, engine=SMALL)  # fmt: skip
        assert (one.resumed, one.summary.frames, one.summary.stored) == (2, 1, 0)
        assert (out / "labels" / "000001.json").is_file()
    assert json.loads((out / "labeling.json").read_text())["resumed"] == 2


def test_a_frame_that_does_not_decode_is_reported_and_the_others_labeled(
    exported_repository,  # noqa: F811
    synth_set,
    tmp_path,
    capsys,
):
    """A corrupt image, a point cloud of the wrong length and a broken calibration: each
    reported by id with its reason (the command's output and labeling.json), the other five
    frames labeled; the command exits 1."""
    data = tmp_path / "synth"
    shutil.copytree(synth_set, data)
    training = data / "training"
    (training / "image_2" / "000001.png").write_bytes(b"not a png")
    points = training / "velodyne" / "000003.bin"
    points.write_bytes(points.read_bytes()[:-3])
    (training / "calib" / "000005.txt").write_text("P2: 1 2 3\n")
    out = tmp_path / "out"
    args = ["label", "--repository", str(exported_repository), "--data", str(data), "--all",
            "--out", str(out), "--tau-hung", str(TAU_HUNG), "--engine", "ray", "--actors", "2",
            "--batch-size", "3"]  # fmt: skip
    assert bounded(main, args) == 1
    err = capsys.readouterr().err
    failed = json.loads((out / "labeling.json").read_text())["failed"]
    assert [f["frame_id"] for f in failed] == ["000001", "000003", "000005"]
    reasons = {f["frame_id"]: f["reason"] for f in failed}
    assert "cannot decode image" in reasons["000001"]
    assert "not a multiple of 16" in reasons["000003"]
    assert "P2 needs 12 numbers" in reasons["000005"]
    for frame_id, reason in reasons.items():
        assert f"{frame_id}: {reason}" in err
    labeled = sorted(p.stem for p in (out / "labels").iterdir())
    assert labeled == ["000000", "000002", "000004", "000006", "000007"]


def test_a_killed_actors_frames_are_retried_and_stored_once(
    exported_repository,  # noqa: F811
    labeler,
    synth_set,
    tmp_path,
    monkeypatch,
):
    """The first batch kills its actor's process (CRASH_ONCE_ENV): Ray restarts the actor and
    retries the batch; every frame is labeled, and stored, once."""
    marker = tmp_path / "crashed"
    monkeypatch.setenv(CRASH_ONCE_ENV, str(marker))
    expected = label_split(labeler, synth_set, ALL, tmp_path / "split", TAU_HUNG, progress=False)
    with LabelStore(tmp_path / "store", "offline") as store:
        got = bounded(label_with_ray, exported_repository, synth_set, ALL, tmp_path / "ray",
                      tau_hung=TAU_HUNG, progress=False, store=store, engine=SMALL)  # fmt: skip
        assert store.stats.frames == 8  # committed once each
    assert marker.is_file()  # an actor did end its process
    assert got.failed == () and got.summary.stored == 8
    same_summary(got.summary, dataclasses.replace(expected, stored=8))  # with the store
    assert result_files(tmp_path / "ray") == result_files(tmp_path / "split")


def test_detmatch_label_engine_options(exported_repository, kitti_sample, tmp_path, capsys):  # noqa: F811
    """--engine ray writes what the default engine writes; its options need it."""
    base = ["label", "--repository", str(exported_repository), "--data", str(kitti_sample),
            "--all", "--tau-hung", str(TAU_HUNG)]  # fmt: skip
    assert main([*base, "--out", str(tmp_path / "inprocess")]) == 0
    ray_args = [*base, "--out", str(tmp_path / "ray"), "--engine", "ray", "--actors", "1",
                "--batch-size", "2"]  # fmt: skip
    assert bounded(main, ray_args) == 0
    assert "labeled 3 frames with model version 000001" in capsys.readouterr().out
    assert result_files(tmp_path / "ray") == result_files(tmp_path / "inprocess")
    assert bounded(main, ray_args) == 0  # resumes: --out is not refused
    assert "skipped 3 frames labeled by this model version already" in capsys.readouterr().out
    assert main([*base, "--out", str(tmp_path / "x"), "--actors", "2"]) == 2
    assert "--actors goes with --engine ray" in capsys.readouterr().err


def test_ray_errors_name_the_fix(exported_repository, kitti_sample, tmp_path):  # noqa: F811
    """Ray missing names the extra; an address nobody answers at is named, within seconds;
    Ray Client's ray://, which Ray Data cannot use, names what to do instead."""
    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    base = ["label", "--repository", str(exported_repository), "--data", str(kitti_sample),
            "--all", "--out", str(tmp_path / "out"), "--engine", "ray"]  # fmt: skip
    for hide_ray, extra, expected in (
        (True, [], "pip install 'detmatch[ray]'"),
        (False, ["--address", f"127.0.0.1:{port}"], f"Ray cluster at 127.0.0.1:{port}"),
        (False, ["--address", f"ray://127.0.0.1:{port}"], "ray job submit"),
    ):
        code = ("import sys; sys.modules['ray'] = None; " if hide_ray else "import sys; ") + (
            "from commands.main import main; sys.exit(main(sys.argv[1:]))"
        )
        env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
        done = subprocess.run([sys.executable, "-c", code, *base, *extra], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=TIMEOUT_S)  # fmt: skip
        assert done.returncode == 2, done.stderr
        assert expected in done.stderr
    with pytest.raises(RayEngineError, match="expected auto or HOST:PORT"):
        RayEngine(address="nowhere")
