"""Errors raised for malformed datasets."""

from __future__ import annotations

__all__ = ["DatasetError"]


class DatasetError(ValueError):
    """A nuScenes-format dataset (or an Occ3D label file) is malformed or incomplete.

    The message always names the file, table, record or token at fault.
    """
