"""CachedDataset: each item is loaded once, the same item comes back, bad indices fail."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import DataLoader, Dataset

from renderworld.data.cache import CachedDataset


class _Counting(Dataset):
    def __init__(self, n: int) -> None:
        self.n, self.loads, self.name = n, [], "counting"

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        self.loads.append(i)
        return {"x": torch.full((2,), float(i)), "meta": {"i": i}}


def test_items_load_once_and_come_back_equal():
    base = _Counting(4)
    data = CachedDataset(base)
    first = [data[i]["x"].clone() for i in range(4)]
    for _ in range(3):  # three more "epochs" through a DataLoader
        for i, batch in enumerate(DataLoader(data, batch_size=1, shuffle=False)):
            torch.testing.assert_close(batch["x"][0], first[i])
    assert sorted(base.loads) == [0, 1, 2, 3] and data.cached == 4
    assert data[-1] is data[3]  # negative indices are the same cached item
    assert data.name == "counting"  # the wrapped dataset's attributes stay reachable


def test_out_of_range_index_fails_clearly_and_caches_nothing():
    data = CachedDataset(_Counting(2))
    with pytest.raises(IndexError, match="index 2 out of range for 2 samples"):
        data[2]
    assert data.cached == 0
