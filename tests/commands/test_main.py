"""The command line a scheduler runs: --version, defaults in every --help, config errors as
exit status 2, `--set` overrides, packaged configs and the refusal to train into an existing
run directory."""

import argparse
import json
import os
import re
import subprocess
import sys
from importlib.metadata import version

import pytest

from commands.common import refuse_existing_run
from commands.export import build_parser as build_export_parser
from commands.main import build_parser, main
from tests.conftest import REPO


def run_cli(*args: str, module: str = "commands.main") -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_version_of_both_commands():
    expected = version("detmatch")
    result = run_cli("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"detmatch {expected}"
    result = run_cli("--version", module="commands.export")
    assert result.returncode == 0 and result.stdout.strip() == f"detmatch-export {expected}"


def test_every_help_and_version_without_torch():
    """The `.[serve]` install has no torch: building both parsers (every --help and --version)
    imports neither torch nor the layers below the commands; a command imports them when it
    runs."""
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "from commands import export, main\n"
        "main.build_parser().format_help(); export.build_parser().format_help()\n"
        "print(' '.join(sorted({m.split('.')[0] for m in sys.modules} & "
        "{'torch', 'serving', 'export', 'grpc', 'onnxruntime'})))\n"
        "main.main(['--version'])"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    imported, printed_version = result.stdout.splitlines()
    assert imported == "torch"  # only the None that blocks it
    assert printed_version == f"detmatch {version('detmatch')}"


def _parsers(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                yield from _parsers(subparser)


@pytest.mark.parametrize("build", [build_parser, build_export_parser])
def test_every_help_shows_the_defaults(build):
    checked = 0
    for parser in _parsers(build()):
        text = " ".join(parser.format_help().split())
        for action in parser._actions:
            default = action.default
            if not action.option_strings or default in (None, [], "", argparse.SUPPRESS):
                continue
            if default is False or "default" in (action.help or ""):
                continue
            assert f"(default: {default})" in text, (parser.prog, action.option_strings)
            checked += 1
    assert checked >= 3


def test_config_errors_exit_2_naming_the_key_before_anything_is_written(tmp_path):
    out = tmp_path / "run"
    cases = [
        (["--set", "train.steps=-5"], r"\[train\] steps must be > 0, got -5"),
        (["--steps", "-5"], r"\[train\] steps must be > 0, got -5"),
        (["--set", "train.lr_3d=0"], r"\[train\] lr_3d must be > 0"),
        (["--set", "data.image_size=[100,96]"], r"\[data\] image_size must be multiples of 16"),
        (["--set", "train.stepz=5"], r"unknown key 'stepz' in \[train\]"),
        (["--set", "steps=5"], r"expected section.key=value"),
        (["--preset", "papper"], r"invalid choice: 'papper'"),
        # A teacher-student run trains [ssl]'s stage: pre-training's schedule keys are refused.
        (
            ["--method", "detmatch", "--pretrained", "runs/pre", "--set", "train.lr_2d=0.01"],
            r"\[train\] lr_2d is pre-training's; a detmatch run .*\(set ssl.lr_2d\)",
        ),
    ]
    for args, message in cases:
        result = run_cli("train", "--config", "tiny", "--out", str(out), *args)
        assert result.returncode == 2, (args, result.stderr)
        assert re.search(message, result.stderr), (args, result.stderr)
        assert "Traceback" not in result.stderr
        assert not out.exists()
    bad = tmp_path / "bad.toml"
    bad.write_text("[train]\nsteps = -5\n")
    result = run_cli("train", "--config", str(bad), "--out", str(out))
    assert result.returncode == 2 and "bad.toml: [train] steps must be > 0" in result.stderr
    result = run_cli("train", "--config", "no-such-config", "--out", str(out))
    assert result.returncode == 2 and "packaged configs: " in result.stderr


def test_train_refuses_an_existing_run_unless_resumed(synth_root, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", "--config", "tiny", "--data", str(synth_root), "--out", str(run),
            "--set", "train.steps=2", "--set", "train.checkpoint_every=1",
            "--set", "train.eval_every=100"]  # fmt: skip
    assert main(args) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["train"]["steps"] == 2 and config["train"]["checkpoint_every"] == 1
    assert config["data"]["root"] == str(synth_root)
    checkpoints = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert checkpoints == ["step_00000001.pt", "step_00000002.pt"]
    metrics = (run / "metrics.jsonl").read_bytes()
    capsys.readouterr()

    assert main(args) == 2
    error = capsys.readouterr().err
    assert "already holds a run" in error and "--resume" in error
    assert (run / "metrics.jsonl").read_bytes() == metrics

    assert main([*args, "--resume"]) == 0
    assert "resumed" in capsys.readouterr().out
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == checkpoints

    # An empty directory is a new run; a file is refused.
    (tmp_path / "empty").mkdir()
    refuse_existing_run(tmp_path / "empty", resume=False)
    (tmp_path / "file").write_text("x")
    assert main(["train", "--config", "tiny", "--out", str(tmp_path / "file")]) == 2
    assert "not a directory" in capsys.readouterr().err
