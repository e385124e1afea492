"""Scheduling: `--every` runs rounds in the foreground and skips while the store holds nothing
new; one scheduler per repository holds its lock and a second one is refused."""

from __future__ import annotations

import pytest

from commands.main import main
from retrain.schedule import parse_period
from serving.repository import list_versions
from tests.retrain.conftest import retrain_args, retrain_process


def test_periods():
    assert parse_period("24h") == 86400 and parse_period("15m") == 900
    assert parse_period("90s") == parse_period("90") == 90 and parse_period("1.5d") == 129600
    for bad in ("", "0s", "-1h", "1w", "h", "1 h 2"):
        with pytest.raises(ValueError, match="expected a period such as"):
            parse_period(bad)


def test_scheduler_skips_an_empty_store_and_refuses_a_second_scheduler(
    tmp_path, repository, round_data, capsys
):
    store = tmp_path / "store"
    store.mkdir()
    args = retrain_args(store, round_data, repository)
    assert main([*args, "--every", "0.01s", "--times", "3"]) == 0
    captured = capsys.readouterr()
    assert captured.out.count(f"skipped: the label store {store} is empty") == 3
    assert captured.err.count("next round in") == 2
    assert list_versions(repository) == ["000001"]

    # A scheduler in the foreground holds the repository's lock while it waits for its next
    # period; a second scheduler (or a one-off round) is refused, naming the holder.
    first = retrain_process(*args, "--every", "24h")
    try:
        line = ""
        while "next round in" not in line:
            line = first.stderr.readline()
            assert line, f"the first scheduler exited: {first.communicate()}"
        assert main(args) == 3
        error = capsys.readouterr().err
        assert "another retraining holds" in error and f"pid {first.pid} " in error
        assert main([*args, "--every", "1h"]) == 3
    finally:
        first.kill()
        first.communicate(timeout=60)
    # The kernel released the lock of the killed scheduler.
    assert main(args) == 0
    assert "is empty" in capsys.readouterr().out


def test_bad_arguments_exit_2_naming_the_problem(tmp_path, repository, round_data, capsys):
    store = tmp_path / "store"
    store.mkdir()
    cases = [
        (["--every", "soon"], "--every 'soon': expected a period"),
        (["--times", "2"], "--times N (N >= 1) goes with --every"),
        (["--set", "retrain.max_map_drop=-1"], "[retrain] max_map_drop must be >= 0"),
        (["--set", "detector3d.widths=[8,8]"], "[detector3d] widths is [8, 8], but version 000001"),
        (["--set", "data.val_split=unlabeled"], "the gate split 'unlabeled' ([data] val_split)"),
    ]
    for extra, message in cases:
        assert main([*retrain_args(store, round_data, repository), *extra, "--force"]) == 2
        assert message in capsys.readouterr().err, extra
    assert main(retrain_args(tmp_path / "none", round_data, repository)) == 2
    assert "--store" in capsys.readouterr().err
    empty = tmp_path / "empty_repository"
    empty.mkdir()
    assert main(retrain_args(store, round_data, empty)) == 2
    assert "has no promoted version" in capsys.readouterr().err
    assert list_versions(repository) == ["000001"]
