"""FrameCache: cached frames equal uncached ones; a changed file or grid invalidates."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, GRIDS
from renderworld.data import OccSequenceDataset, load_infos, save_occ3d_labels
from renderworld.data.frame_cache import FrameCache
from tests.converter.datasets_for_tests import build_and_convert

COARSE = GRIDS["coarse"]


def _labels(path, value: int) -> None:
    sem = np.full((200, 200, 16), FREE_ID, np.uint8)
    sem[:8, :8, :2] = value
    mask = np.zeros_like(sem)
    mask[:4] = 1
    save_occ3d_labels(path, sem, mask, mask)


def test_entry_is_computed_once_then_read(tmp_path):
    src = tmp_path / "labels.npz"
    _labels(src, 4)
    cache = FrameCache(tmp_path / "cache")
    calls = []

    def compute(p):
        calls.append(p)
        return np.full(COARSE.shape, 4, np.uint8), np.ones(COARSE.shape, bool)

    a = cache.get(src, COARSE, compute)
    b = FrameCache(tmp_path / "cache").get(src, COARSE, compute)  # a new process's view
    assert len(calls) == 1 and cache.misses == 1
    assert np.array_equal(a[0], b[0]) and b[1].dtype == bool and b[1].all()


def test_a_changed_file_or_grid_invalidates(tmp_path):
    src = tmp_path / "labels.npz"
    _labels(src, 4)
    cache = FrameCache(tmp_path / "cache")
    k = cache.key(src, COARSE)
    assert cache.key(src, GRIDS["half"]) != k
    st = src.stat()
    _labels(src, 9)  # new content (same size: only the hash may tell)
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns))  # even with the old mtime
    assert cache.key(src, COARSE) != k
    with pytest.raises(FileNotFoundError, match="nope.npz: occupancy file not found"):
        cache.key(tmp_path / "nope.npz", COARSE)
    with pytest.raises(TypeError, match="root: expected a folder path"):
        FrameCache(3)


def test_compute_result_is_checked(tmp_path):
    src = tmp_path / "labels.npz"
    _labels(src, 4)
    with pytest.raises(ValueError, match=r"compute: expected two \(50, 50, 4\) arrays"):
        FrameCache(tmp_path / "c").get(src, COARSE, lambda p: (np.zeros((2, 2, 2)),) * 2)


@pytest.fixture(scope="module")
def own_dataset(tmp_path_factory):
    """A converted left-turn dataset of this module only (the test rewrites a label file)."""
    root = tmp_path_factory.mktemp("frame_cache") / "ds"
    return root, build_and_convert(root, scene_names=("scene-0061", "scene-0103"), ego_path="left")


def test_sequence_items_with_the_cache_equal_uncached_and_follow_file_changes(
    own_dataset, tmp_path
):
    root, out = own_dataset
    infos = load_infos(out, "train")
    cache_dir = tmp_path / "frames"
    plain = OccSequenceDataset(infos, root, history=2, future=2, grid="coarse")
    cold = OccSequenceDataset(infos, root, history=2, future=2, grid="coarse",
                              frame_cache=cache_dir, cache_frames=0)  # fmt: skip
    for i in range(len(plain)):
        a, b = plain[i], cold[i]
        for key in ("occ", "mask_camera", "ego_displacements", "history_poses"):
            assert torch.equal(a[key], b[key]), key
    assert cold.frame_cache.misses == len(infos) and cold.frame_cache.hits > 0
    warm = OccSequenceDataset(infos, root, history=2, future=2, grid="coarse",
                              frame_cache=cache_dir, cache_frames=0)  # fmt: skip
    assert torch.equal(warm[0]["occ"], plain[0]["occ"])
    assert warm.frame_cache.misses == 0
    # Rewrite the first frame's labels: the cached entry is not used any more.
    first = root / infos["occ_path"].iloc[0]
    before = plain[0]["occ"][0]
    _labels(first, 9)
    item = warm[0]
    assert warm.frame_cache.misses == 1
    assert (item["occ"][0] == 9).any() and not (before == 9).any()
