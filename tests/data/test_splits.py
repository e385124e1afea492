import pytest

from detmatch.cli import main
from detmatch.data.kitti import read_image_set, write_image_set
from detmatch.data.splits import choose_labeled, split_names


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
