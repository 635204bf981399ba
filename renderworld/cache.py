"""The package's on-disk cache root: one setting for every cache.

``$RENDERWORLD_CACHE_DIR`` when set (and not empty), else ``~/.cache/renderworld``. Under it:
``tables/`` (validated nuScenes tables, :class:`renderworld.data.TableCache`), ``frames/`` (the
world model's down-sampled frame cache) and ``splat_ext/`` (the compiled CPU rasterizer).

The earlier name ``$RENDERWORLD_CACHE`` (read by the rasterizer's build only) still works when
``RENDERWORLD_CACHE_DIR`` is unset, with a :class:`DeprecationWarning`.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

__all__ = ["CACHE_ENV", "cache_root"]

#: The environment variable that moves every cache of the package.
CACHE_ENV = "RENDERWORLD_CACHE_DIR"
_DEPRECATED_ENV = "RENDERWORLD_CACHE"


def cache_root() -> Path:
    """The cache root: ``$RENDERWORLD_CACHE_DIR`` or ``~/.cache/renderworld``.

    Returns:
        The folder (not created here).
    """
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env)
    old = os.environ.get(_DEPRECATED_ENV)
    if old:
        warnings.warn(
            f"${_DEPRECATED_ENV} is deprecated: set ${CACHE_ENV} instead (it moves every cache "
            f"of the package); using {old}",
            DeprecationWarning,
            stacklevel=2,
        )
        return Path(old)
    return Path.home() / ".cache" / "renderworld"
