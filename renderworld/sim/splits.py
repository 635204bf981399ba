"""Scene-name patterns → the train/val split lists a simulated dataset ships as ``splits.json``.

The infos builder (``data_converters/splits.py``) reads ``<version>/splits.json``
(``{split: [scene names]}``); a :class:`~renderworld.sim.scene.SimConfig` states it as
``{split: [fnmatch patterns]}`` so that a preset of many scenes needs no name lists.
"""

from __future__ import annotations

import json
from fnmatch import fnmatchcase

__all__ = ["match_splits", "splits_json"]


def match_splits(patterns, names: list[str]) -> dict[str, list[str]]:
    """``{split: [scene names]}``: each name goes to the one split with a matching pattern.

    Args:
        patterns: ``{split: [fnmatch patterns]}``, e.g. ``{"val": ["scene-6*"]}``.
        names: scene names in dataset order.

    Raises:
        ValueError: naming ``splits`` when ``patterns`` is malformed or a name matches no split
            or several.
    """
    ok = isinstance(patterns, dict) and all(
        isinstance(k, str) and isinstance(v, list) and all(isinstance(p, str) for p in v)
        for k, v in patterns.items()
    )
    if not ok or not patterns:
        raise ValueError(f"splits: expected {{split: [scene-name patterns]}}, got {patterns!r}")
    out: dict[str, list[str]] = {k: [] for k in patterns}
    for name in names:
        hit = [k for k, pats in patterns.items() if any(fnmatchcase(name, p) for p in pats)]
        if len(hit) != 1:
            raise ValueError(
                f"splits: expected exactly one split matching scene {name!r}, got {hit!r}"
            )
        out[hit[0]].append(name)
    return out


def splits_json(lists: dict[str, list[str]]) -> bytes:
    """``splits.json`` bytes (sorted-key JSON, one-space indent) of split lists."""
    return json.dumps(lists, indent=1, sort_keys=True).encode()
