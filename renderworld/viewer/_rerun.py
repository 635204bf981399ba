"""The one place that imports Rerun: a clear error when the optional extra is missing."""

from __future__ import annotations

import importlib
import importlib.util

import numpy as np

from renderworld.constants import OCC3D_CLASSES, OCC3D_COLORS

__all__ = ["INSTALL_HINT", "rerun_available", "require_rerun", "class_annotations", "transform"]

#: What to run when Rerun is missing.
INSTALL_HINT = "pip install 'renderworld[viz]' (or: pip install rerun-sdk)"


def rerun_available() -> bool:
    """Whether ``rerun`` (the ``rerun-sdk`` package) can be imported, without importing it."""
    return importlib.util.find_spec("rerun") is not None


def require_rerun():
    """Import and return the ``rerun`` module.

    Raises:
        ImportError: when ``rerun-sdk`` is not installed (the message says how to install it).
    """
    try:
        return importlib.import_module("rerun")
    except ImportError as err:
        raise ImportError(f"the scene viewer needs rerun-sdk: {INSTALL_HINT}") from err


def class_annotations(rr):
    """``rr.AnnotationContext`` giving every Occ3D class id (0..17) its name and colour.

    Logged once (static) at ``world``, it colours and labels every ``class_ids`` below it, so
    points and boxes store 2-byte class ids instead of 4-byte colours.
    """
    return rr.AnnotationContext(
        [
            rr.AnnotationInfo(id=i, label=name, color=tuple(int(c) for c in colour))
            for i, (name, colour) in enumerate(zip(OCC3D_CLASSES, OCC3D_COLORS, strict=True))
        ]
    )


def transform(rr, parent_from_child: np.ndarray):
    """``rr.Transform3D`` of a [4, 4] rigid transform (maps child coordinates to the parent)."""
    m = np.asarray(parent_from_child, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"parent_from_child: expected a [4, 4] matrix, got {m.shape}")
    return rr.Transform3D(
        translation=m[:3, 3].astype(np.float32), mat3x3=m[:3, :3].astype(np.float32)
    )
