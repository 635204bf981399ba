"""Same seed and config give byte-identical datasets; another seed gives another dataset."""

from __future__ import annotations

from pathlib import Path

from renderworld.sim import REPORT_NAME, simulate
from tools.make_fixtures import config_from_preset


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != REPORT_NAME  # the report holds wall-clock timings
    }


def test_tiny_is_byte_identical_for_the_same_seed(tiny_dataset, tmp_path):
    simulate(config_from_preset("tiny"), tmp_path / "again", progress=False)
    a, b = _files(tiny_dataset), _files(tmp_path / "again")
    assert sorted(a) == sorted(b) and len(a) > 100
    different = [k for k in a if a[k] != b[k]]
    assert different == []


def test_another_seed_changes_the_data(tmp_path):
    small = dict(keyframes=2, num_scenes=1, image_size="64x36")
    simulate(config_from_preset("tiny", seed=1, **small), tmp_path / "s1", progress=False)
    simulate(config_from_preset("tiny", seed=2, **small), tmp_path / "s2", progress=False)
    a, b = _files(tmp_path / "s1"), _files(tmp_path / "s2")
    lidar = [k for k in a if k.endswith(".pcd.bin")]
    assert lidar and all(a[k] != b.get(k) for k in lidar)
