"""On-disk cache of what a grid makes of each occupancy frame (down-sampled labels and mask).

Reading a ``labels.npz`` at 200x200x16 (zlib) and down-sampling it to the training grid is most
of a world-model data item; every window re-reads eleven of them. :class:`FrameCache` stores the
result once per (file, grid) as an uncompressed ``.npy`` (a copy of two uint8 volumes) and
serves it from then on.

Key: the file's resolved path, its size, its modification time (ns), a BLAKE2 hash of its
bytes, the grid (name, shape, range) and :data:`FRAME_CACHE_VERSION` (bumped when the
down-sampling rule changes). Any change of the file or the grid gives a new key, so a stale
entry is never read; the old one is simply left behind (delete the folder to reclaim it).
Writes are atomic, so concurrent readers see a whole entry or none.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from renderworld.constants import GridSpec
from renderworld.data.atomic import atomic_write

__all__ = ["FRAME_CACHE_VERSION", "FrameCache"]

#: Part of every key: bump when what is cached for a (file, grid) changes.
FRAME_CACHE_VERSION = 1

_CHUNK = 1 << 20


def _file_hash(path: Path) -> str:
    h = hashlib.blake2b(digest_size=16)
    with path.open("rb") as f:
        while block := f.read(_CHUNK):
            h.update(block)
    return h.hexdigest()


class FrameCache:
    """Down-sampled (labels, camera mask) of occupancy files, cached in a folder.

    Args:
        root: cache folder (created on first write).

    Attributes:
        hits / misses: entries served from the folder / computed since construction.
    """

    def __init__(self, root: str | os.PathLike) -> None:
        if not isinstance(root, (str, os.PathLike)):
            raise TypeError(f"root: expected a folder path, got {type(root).__name__}")
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise ValueError(f"root: {self.root} exists and is not a folder")
        self.hits = 0
        self.misses = 0

    def key(self, path: str | os.PathLike, grid: GridSpec) -> str:
        """Hex key of ``path`` (as it is now on disk) on ``grid``.

        Raises:
            FileNotFoundError: naming the file when it does not exist.
        """
        path = Path(path).resolve()
        try:
            st = path.stat()
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: occupancy file not found") from None
        parts = (
            str(path), st.st_size, st.st_mtime_ns, _file_hash(path), grid.name,
            tuple(grid.shape), tuple(grid.range_min), tuple(grid.range_max), FRAME_CACHE_VERSION,
        )  # fmt: skip
        return hashlib.blake2b(repr(parts).encode(), digest_size=16).hexdigest()

    def entry(self, path: str | os.PathLike, grid: GridSpec) -> Path:
        """The cache file that holds (or will hold) ``path`` on ``grid``."""
        k = self.key(path, grid)
        return self.root / k[:2] / f"{k}.npy"

    def get(
        self,
        path: str | os.PathLike,
        grid: GridSpec,
        compute: Callable[[Path], tuple[np.ndarray, np.ndarray]],
    ) -> tuple[np.ndarray, np.ndarray]:
        """(labels uint8 [X,Y,Z], camera mask bool [X,Y,Z]) of ``path`` on ``grid``.

        Args:
            path: the occupancy file.
            grid: the grid the arrays are on.
            compute: ``compute(path)`` -> (labels, mask) when the entry is missing; its result
                is stored and returned.
        """
        file = self.entry(path, grid)
        if file.is_file():
            try:
                both = np.load(file, allow_pickle=False)
            except (OSError, ValueError):
                both = None  # a damaged entry: recompute and overwrite
            if both is not None and both.shape == (2, *grid.shape) and both.dtype == np.uint8:
                self.hits += 1
                return both[0], both[1].astype(bool)
        labels, mask = compute(Path(path))
        labels, mask = np.asarray(labels), np.asarray(mask)
        if labels.shape != tuple(grid.shape) or mask.shape != tuple(grid.shape):
            raise ValueError(
                f"compute: expected two {tuple(grid.shape)} arrays for {path}, got "
                f"{labels.shape} and {mask.shape}"
            )
        both = np.stack([labels.astype(np.uint8), mask.astype(np.uint8)])
        file.parent.mkdir(parents=True, exist_ok=True)

        def write(tmp: str) -> None:
            with open(tmp, "wb") as f:  # a handle: np.save would append ".npy" to a name
                np.save(f, both)

        atomic_write(file, write, suffix=".tmp")
        self.misses += 1
        return both[0], both[1].astype(bool)
