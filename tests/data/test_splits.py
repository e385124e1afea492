import pytest

from commands.main import main
from detmatch.data.kitti import read_image_set, write_image_set
from detmatch.data.splits import choose_labeled, dev_name, split_names


@pytest.fixture
def layout(tmp_path):
    (tmp_path / "training").mkdir()
    ids = [f"{i:06d}" for i in range(200)]
    write_image_set(tmp_path / "ImageSets" / "train.txt", ids)
    return tmp_path, ids


@pytest.mark.parametrize("fraction", [0.01, 0.02, 0.2])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_split_partitions_the_train_frames(layout, fraction, seed):
    root, ids = layout
    assert (
        main(["split", "--data", str(root), "--fraction", str(fraction), "--seed", str(seed)]) == 0
    )
    labeled_name, unlabeled_name = split_names(fraction, seed)
    labeled = read_image_set(root / "ImageSets" / f"{labeled_name}.txt")
    unlabeled = read_image_set(root / "ImageSets" / f"{unlabeled_name}.txt")
    assert len(labeled) == round(fraction * len(ids))
    assert sorted(labeled + unlabeled) == ids
    assert not set(labeled) & set(unlabeled)


def test_split_is_seeded_and_nested():
    ids = [f"{i:06d}" for i in range(500)]
    small, _ = choose_labeled(ids, 0.02, seed=3)
    large, _ = choose_labeled(ids, 0.2, seed=3)
    assert choose_labeled(ids, 0.02, seed=3)[0] == small
    assert choose_labeled(ids, 0.02, seed=4)[0] != small
    assert set(small) <= set(large)


def test_split_keeps_one_frame_on_each_side():
    assert [len(part) for part in choose_labeled(["a", "b", "c"], 0.01, 0)] == [1, 2]
    assert [len(part) for part in choose_labeled(["a", "b", "c"], 0.99, 0)] == [2, 1]


def test_bad_split_arguments(layout, capsys):
    root, _ = layout
    assert main(["split", "--data", str(root), "--fraction", "1.5"]) == 2
    assert "fraction must be in (0, 1)" in capsys.readouterr().err
    assert main(["split", "--data", str(root), "--fraction", "0.1", "--source", "nope"]) == 2
    assert "no split 'nope'" in capsys.readouterr().err


def test_the_dev_split_is_disjoint_and_shared_by_every_seed(layout):
    """dev is held out first (the same frames for every seed); the labeled subset and the
    unlabeled pool come from the rest; val (another split) is not touched."""
    root, ids = layout
    write_image_set(root / "ImageSets" / "val.txt", [f"v{i:05d}" for i in range(50)])
    devs = []
    for seed in (0, 1):
        args = ["split", "--data", str(root), "--fraction", "0.05", "--seed", str(seed)]
        assert main([*args, "--dev-fraction", "0.1"]) == 0
        dev = read_image_set(root / "ImageSets" / f"{dev_name(0.1)}.txt")
        labeled_name, unlabeled_name = split_names(0.05, seed, dev_fraction=0.1)
        labeled = read_image_set(root / "ImageSets" / f"{labeled_name}.txt")
        unlabeled = read_image_set(root / "ImageSets" / f"{unlabeled_name}.txt")
        val = read_image_set(root / "ImageSets" / "val.txt")
        assert len(dev) == 20 and len(labeled) == 10  # fractions of all train frames
        assert not set(dev) & set(labeled) and not set(dev) & set(unlabeled)
        assert not set(dev) & set(val) and not set(labeled) & set(unlabeled)
        assert sorted(dev + labeled + unlabeled) == ids
        devs.append(dev)
    assert devs[0] == devs[1]


def test_a_split_that_leaves_no_unlabeled_frame_is_refused_and_writes_nothing(tmp_path, capsys):
    # 12 train frames: the dev set takes 11 and the one left is labeled.
    root = tmp_path
    (root / "training").mkdir()
    write_image_set(root / "ImageSets" / "train.txt", [f"{i:06d}" for i in range(12)])
    before = sorted(p.name for p in (root / "ImageSets").iterdir())
    argv = ["split", "--data", str(root), "--fraction", "0.01", "--seed", "0"]
    assert main([*argv, "--dev-fraction", "0.99"]) == 2
    error = capsys.readouterr().err
    assert "leaves no unlabeled frame" in error and "--dev-fraction 0.99" in error
    assert sorted(p.name for p in (root / "ImageSets").iterdir()) == before
