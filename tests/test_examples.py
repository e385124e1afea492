"""examples/label_frame.py answers a client's mistakes with one line, not a traceback."""

import subprocess
import sys

import pytest

from tests.conftest import REPO


@pytest.mark.parametrize(
    "frame, expected",
    [("000001", "label_frame: UNAVAILABLE: "), ("999999", "label_frame: error: no such file: ")],
)
def test_label_frame_example_reports_errors_in_one_line(kitti_sample, frame, expected):
    done = subprocess.run(
        [sys.executable, str(REPO / "examples" / "label_frame.py"), "--target", "127.0.0.1:1",
         "--data", str(kitti_sample), "--frame", frame],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 1
    assert done.stderr.startswith(expected) and done.stderr.count("\n") == 1, done.stderr
    assert "Traceback" not in done.stderr
