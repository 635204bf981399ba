"""Atomic file writes: a temporary file in the target's folder, then ``os.replace``.

A reader never sees a half-written file, and an interrupted write leaves the previous file (or
none) in place.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_write"]


def atomic_write(path, write: Callable[[str], object], suffix: str = ".tmp") -> Path:
    """Write ``path`` atomically through ``write(tmp_path)``.

    Args:
        path: the final file; its parent folders are created.
        write: writes the whole file to the temporary path it is given.
        suffix: the temporary file's suffix (writers like ``np.savez`` need ``.npz``).

    Returns:
        ``path`` as a Path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
