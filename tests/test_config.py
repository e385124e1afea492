"""The experiment config: range checks naming section and key, `--set` overrides and the
configs shipped inside the package."""

import importlib.resources
import re

import pytest

from detmatch.config import (
    PRESETS,
    ConfigError,
    DataConfig,
    ExperimentConfig,
    TrainConfig,
    apply_overrides,
    apply_preset,
    config_from_dict,
    config_to_dict,
    load_config,
    packaged_configs,
    parse_override,
    refuse_pretraining_overrides,
    teacher_student_config,
)
from detmatch.matching_policy import MatchingPolicy
from tests.conftest import REPO

# (section, key, a value out of range): each must be refused with a message naming both.
OUT_OF_RANGE = [
    ("data", "image_size", [0, 96]),
    ("data", "image_size", [100, 96]),  # not a multiple of the 2D backbone's stride
    ("data", "num_workers", -1),
    ("data", "classes", []),
    ("data", "classes", ["Car", "Car"]),
    ("data", "classes", ["Car", "Traffic sign"]),
    ("data", "train_split", ""),
    ("data", "root", ""),
    ("data", "train_boxes_2d", "silhouette"),
    ("detector2d", "widths", [8, 0, 16, 32]),
    ("detector2d", "depths", [1, 1, 1]),
    ("detector2d", "head_width", 0),
    ("detector2d", "max_detections", 0),
    ("detector2d", "score_threshold", 1.5),
    ("detector2d", "size_weight", -0.1),
    ("detector3d", "pillar_size", [0.0, 0.4]),
    ("detector3d", "pillar_size", [0.3, 0.4]),  # 51.2 m is not a multiple of 0.3 m
    ("detector3d", "point_cloud_range", [0.0, -25.6, -3.0, 0.0, 25.6, 1.0]),
    ("detector3d", "max_pillars", 0),
    ("detector3d", "max_points_per_pillar", -1),
    ("detector3d", "out_stride", 0),
    ("detector3d", "score_threshold", -0.1),
    ("detector3d", "regression_weight", float("nan")),
    ("train", "steps", -5),
    ("train", "steps", 0),
    ("train", "batch_size", 0),
    ("train", "lr_2d", 0.0),
    ("train", "lr_3d", -0.001),
    ("train", "lr_3d", float("inf")),
    ("train", "momentum_2d", 1.0),
    ("train", "betas_3d", [0.95, 1.2]),
    ("train", "weight_decay_2d", -1e-4),
    ("train", "warmup_steps", -1),
    ("train", "grad_clip", 0.0),
    ("train", "eval_every", 0),
    ("train", "checkpoint_every", 0),
    ("train", "log_every", -1),
    ("train", "seed", -1),
    ("train", "flip_probability", 1.5),
    ("ssl", "method", "pseudo"),
    ("ssl", "tau_3d", 1.2),
    ("ssl", "tau_2d", -0.7),
    ("ssl", "tau_3d_unmatched", 1.1),
    ("ssl", "tau_hung", float("nan")),
    ("ssl", "pseudo_label_weight", -1.0),
    ("ssl", "consistency_l1_weight", -20.0),
    ("ssl", "ema_offset", 0),
    ("ssl", "ema_max_decay", 1.0),
    ("ssl", "student_scale", [1.05, 0.95]),
    ("ssl", "student_scale", [0.0, 1.05]),
    ("ssl", "unlabeled_split", "a b"),
    ("retrain", "steps", 0),
    ("retrain", "max_map_drop", -1.0),
    ("retrain", "max_map_drop", float("inf")),
    ("retrain", "stored_labels", "pseudo"),
]


@pytest.mark.parametrize(("section", "key", "value"), OUT_OF_RANGE)
def test_out_of_range_values_are_refused_naming_section_and_key(section, key, value):
    raw = config_to_dict(load_config("tiny"))
    raw[section][key] = value
    with pytest.raises(ConfigError, match=re.escape(f"[{section}] {key} ")):
        config_from_dict(raw)


def test_detmatch_defaults_are_what_won_on_dev():
    """LiDAR-only labels above 0.6 (their 2D side protected: not an option) and no consistency
    loss (BENCHMARKS.md, issue 14)."""
    ssl = load_config("tiny").ssl
    assert MatchingPolicy.from_config(ssl).tau_3d_unmatched == 0.6
    assert not ssl.consistency_box and not ssl.consistency_class
    off = apply_overrides(load_config("tiny"), ["ssl.tau_3d_unmatched=1.0"]).ssl
    assert MatchingPolicy.from_config(off).tau_3d_unmatched is None


@pytest.mark.parametrize(
    ("key", "value"),
    [("consistency_reduction", "pairs"), ("consistency_nms", False),
     ("pseudo_2d_normalizer", "pseudo-labels"), ("consistency_targets", "teacher"),
     ("ignore_unmatched_score_3d", 1.0), ("ignore_unmatched_score_2d", 1.0),
     ("lidar_only_ignore_2d", True)],
)  # fmt: skip
def test_a_saved_config_with_a_retired_key_loads_at_the_behaviour_kept(key, value):
    """Runs saved before the options that dev decided were deleted (checkpoints, retraining
    states) still load where they hold what the code still does; any other value is refused,
    naming the commit that has the option."""
    raw = config_to_dict(load_config("tiny"))
    assert config_from_dict({**raw, "ssl": {**raw["ssl"], key: value}}) == load_config("tiny")
    other = {"consistency_reduction": "frames", "consistency_nms": True,
             "pseudo_2d_normalizer": "labeled", "consistency_targets": "labels-projected",
             "ignore_unmatched_score_3d": 0.3, "ignore_unmatched_score_2d": 0.3,
             "lidar_only_ignore_2d": False}[key]  # fmt: skip
    with pytest.raises(ConfigError, match=rf"\[ssl\] {key} = .* commit 651fd4f has it"):
        config_from_dict({**raw, "ssl": {**raw["ssl"], key: other}})
    with pytest.raises(ConfigError, match=f"unknown key '{key}'"):
        apply_overrides(load_config("tiny"), [f"ssl.{key}={other}"])


def test_the_paper_presets_lidar_only_ignore_2d_false_still_loads():
    """lidar_only_ignore_2d = false did nothing without LiDAR-only labels (tau_3d_unmatched 1.0,
    the paper preset's runs)."""
    raw = config_to_dict(load_config("tiny"))
    ssl = {**raw["ssl"], "lidar_only_ignore_2d": False, "tau_3d_unmatched": 1.0}
    loaded = config_from_dict({**raw, "ssl": ssl}).ssl
    assert MatchingPolicy.from_config(loaded).tau_3d_unmatched is None


def test_code_paths_get_the_same_checks():
    with pytest.raises(ConfigError, match=r"\[train\] steps must be > 0, got -5"):
        TrainConfig(steps=-5)
    with pytest.raises(ConfigError, match=r"\[data\] num_workers must be >= 0"):
        DataConfig(num_workers=-2)
    with pytest.raises(ConfigError, match=r"\[train\] lr_2d must be > 0"):
        ExperimentConfig().replace("train", lr_2d=0.0)
    with pytest.raises(ConfigError, match=r"\[data\] image_size must be multiples of 16"):
        ExperimentConfig(data=DataConfig(image_size=(320, 100)))


def test_every_shipped_config_is_valid_and_round_trips():
    names = packaged_configs()
    assert {"tiny", "synth_cpu", "ssl_cpu", "ssl_cpu_projected"} <= set(names)
    for name in names:
        config = load_config(name)
        assert config_from_dict(config_to_dict(config)) == config


def test_packaged_configs_are_the_repository_files():
    """One source of truth: configs/*.toml is what ships as detmatch.configs."""
    packaged = importlib.resources.files("detmatch.configs")
    files = sorted(p.name for p in (REPO / "configs").glob("*.toml"))
    assert files == sorted(f"{name}.toml" for name in packaged_configs())
    for name in files:
        assert (packaged / name).read_text() == (REPO / "configs" / name).read_text()


def test_configs_load_by_name_or_path(tmp_path, monkeypatch):
    by_name = load_config("tiny")
    assert by_name == load_config("tiny.toml") == load_config(REPO / "configs" / "tiny.toml")
    assert by_name.train.steps == 6
    with pytest.raises(FileNotFoundError, match=r"no packaged config .*packaged configs: .*tiny"):
        load_config("tinyy")
    with pytest.raises(FileNotFoundError, match="no config file"):
        load_config(tmp_path / "missing.toml")
    # A file that exists wins over a packaged name.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tiny").write_text("[train]\nsteps = 3\n")
    assert load_config("tiny").train.steps == 3
    (tmp_path / "bad.toml").write_text("[train]\nsteps = -5\n")
    with pytest.raises(ConfigError, match=r"bad.toml: \[train\] steps must be > 0, got -5"):
        load_config("bad.toml")


def test_overrides_parse_toml_literals_and_bare_strings():
    assert parse_override("train.steps=100") == ("train", "steps", 100)
    assert parse_override("train.lr_2d = 0.02") == ("train", "lr_2d", 0.02)
    assert parse_override("data.image_size=[320, 96]") == ("data", "image_size", [320, 96])
    assert parse_override("ssl.method=detmatch") == ("ssl", "method", "detmatch")
    assert parse_override('data.root="a b"') == ("data", "root", "a b")
    assert parse_override("ssl.photometric=false") == ("ssl", "photometric", False)
    for bad in ("train.steps", "steps=1", ".steps=1", "train.=1", "train.a.b=1"):
        with pytest.raises(ConfigError, match="expected section.key=value"):
            parse_override(bad)


def test_overrides_apply_together_and_are_validated():
    base = load_config("tiny")
    config = apply_overrides(
        base,
        [
            "train.steps=3",
            "ssl.method=confidence",
            "data.val_split=2024",  # a string key keeps the text: the split "2024"
            "detector2d.widths=[8, 16, 32]",  # with depths, in one go: valid together
            "detector2d.depths=[1, 1, 1]",
            "data.image_size=[320, 96]",
        ],
    )
    assert config.train.steps == 3 and config.ssl.method == "confidence"
    assert config.data.val_split == "2024" and config.detector2d.widths == (8, 16, 32)
    assert config.detector3d == base.detector3d
    assert apply_overrides(base, []) == base
    with pytest.raises(ConfigError, match=r"unknown section \[trian\]; known sections: data"):
        apply_overrides(base, ["trian.steps=3"])
    with pytest.raises(ConfigError, match=r"unknown key 'stepz' in \[train\]; known keys: .*steps"):
        apply_overrides(base, ["train.stepz=3"])
    with pytest.raises(ConfigError, match=r"\[train\] steps must be > 0, got -5"):
        apply_overrides(base, ["train.steps=-5"])
    with pytest.raises(ConfigError, match=r"\[train\] steps must be int, got 'many'"):
        apply_overrides(base, ["train.steps=many"])
    with pytest.raises(ConfigError, match=r"\[detector2d\] depths must be a list of one entry"):
        apply_overrides(base, ["detector2d.widths=[8, 16, 32]"])


def test_a_teacher_student_run_takes_the_ssl_stage_schedule_and_pretraining_keeps_train():
    pretraining = apply_overrides(
        load_config("ssl_cpu"), ["train.steps=3000", "ssl.steps=1200", "ssl.lr_2d=0.004"]
    )
    assert teacher_student_config(pretraining) == pretraining  # labeled-only
    for method in ("labeled-only-control", "confidence", "detmatch"):
        run = teacher_student_config(pretraining.replace("ssl", method=method))
        train = run.train
        assert (train.steps, train.lr_2d, train.lr_3d) == (1200, 0.004, run.ssl.lr_3d)
        assert train.warmup_steps == run.ssl.warmup_steps
        assert (train.schedule_2d, train.schedule_3d) == ("constant", "constant")
        assert train.batch_size == pretraining.train.batch_size  # the rest of [train] stays
        # A run's saved config can start the next run (a retraining round): no compounding.
        assert teacher_student_config(run) == run
    # Overriding pre-training's schedule for a teacher-student run is refused, naming [ssl].
    refuse_pretraining_overrides(pretraining, ["train.lr_2d=0.1"])  # labeled-only: its own
    detmatch = pretraining.replace("ssl", method="detmatch")
    refuse_pretraining_overrides(detmatch, ["train.batch_size=2", "ssl.lr_2d=0.1"])
    with pytest.raises(ConfigError, match=r"\[train\] steps is pre-training's.*set ssl.steps"):
        refuse_pretraining_overrides(detmatch, ["train.batch_size=2", "train.steps=10"])
    with pytest.raises(ConfigError, match=r"schedule_3d .*constant after the warm-up"):
        refuse_pretraining_overrides(detmatch, ["train.schedule_3d=onecycle"])
    # The shipped benchmark config's stage is the one dev chose: 1,200 steps at 0.1x its
    # pre-training rates; every shipped config's stage is at 0.1x its own, as are the defaults.
    assert load_config("ssl_cpu").ssl.steps == 1200
    for config in [*map(load_config, packaged_configs()), ExperimentConfig()]:
        assert config.ssl.lr_2d == pytest.approx(config.train.lr_2d / 10)
        assert config.ssl.lr_3d == pytest.approx(config.train.lr_3d / 10)


def test_the_paper_preset_restores_the_published_method_whatever_the_config_says():
    """`--preset paper` must give the paper's loss even from a config that changed it."""
    changed = apply_overrides(
        load_config("tiny"),
        ["ssl.consistency_box=false", "ssl.consistency_class=false", "ssl.tau_hung=-2.0",
         "detector3d.refine=true", "train.steps=7", "ssl.tau_3d_unmatched=0.6"],
    )  # fmt: skip
    paper = apply_preset(changed, "paper")
    assert paper.ssl.method == "detmatch"
    assert paper.ssl.consistency_box and paper.ssl.consistency_class
    assert paper.ssl.tau_hung == -1.5
    assert not paper.detector3d.refine
    # The paper's rule: only matched objects in view are labels (so no LiDAR-only labels whose
    # projections the 2D student would ignore); every unmatched detection is background.
    assert paper.ssl.tau_3d_unmatched == 1.0
    assert paper.train.steps == 7  # what the preset does not name stays
    assert set(PRESETS) >= {"paper"}
    with pytest.raises(ConfigError, match="unknown preset 'papper'; known presets: paper"):
        apply_preset(changed, "papper")
