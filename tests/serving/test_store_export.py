import pytest

from serving.store import export_store


def test_exporting_a_store_that_does_not_exist_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no label store at .*nosuch"):
        export_store(tmp_path / "nosuch", tmp_path / "out")
    assert not (tmp_path / "out").exists()
