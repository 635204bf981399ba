import pytest

from renderworld.data.atomic import atomic_write


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "sub" / "labels.npz"
    atomic_write(target, lambda tmp: open(tmp, "w").write("old"), ".tmp.npz")

    def broken(tmp):
        with open(tmp, "w") as f:
            f.write("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, broken, ".tmp.npz")
    assert target.read_text() == "old"
    assert sorted(p.name for p in target.parent.iterdir()) == ["labels.npz"]
