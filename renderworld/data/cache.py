"""Keep a dataset's items in memory after their first load.

Decoding six JPEGs, resizing them and densifying the label maps costs 23.7 ms per Img2Occ
sample of the mini experiment on a 2-core CPU (measured at 28c809a), a tenth of its training
step, and the same samples come back every epoch, every validation and in the threshold
search. Items must be
deterministic (Img2OccDataset's are: no random augmentation in the dataset). The cache lives
in the process that reads the items: use it with DataLoader ``num_workers=0`` (worker
processes would each fill a copy that dies with them).

Memory: the whole split once; measured for ``experiment=img2occ_mini`` (6 images of
3x128x224 float32, 18 label maps of 56x100, the Occ3D grid): 3.15 MiB per sample, 605 MiB for
the 192 train and 114 MiB for the 48 val samples.
"""

from __future__ import annotations

from typing import Any

from torch.utils.data import Dataset

__all__ = ["CachedDataset"]


class CachedDataset(Dataset):
    """Map-style dataset wrapper returning each item from memory after its first load.

    Args:
        dataset: A map-style dataset with deterministic items.

    Attributes:
        dataset: The wrapped dataset (its attributes stay reachable through this wrapper).
    """

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset
        self._items: dict[int, Any] = {}

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Any:
        n = len(self)
        i = int(index)
        if not -n <= i < n:
            raise IndexError(f"index {index} out of range for {n} samples")
        i %= n
        item = self._items.get(i)
        if item is None:
            item = self.dataset[i]
            self._items[i] = item
        return item

    @property
    def cached(self) -> int:
        """Number of items held in memory."""
        return len(self._items)

    def __getattr__(self, name: str) -> Any:
        # Only called for attributes this wrapper lacks: infos, grid, ... of the dataset.
        if name == "dataset":
            raise AttributeError(name)
        return getattr(self.dataset, name)
