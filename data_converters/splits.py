"""Train/val split of scenes by name.

Source, in order: ``<dataroot>/<version>/splits.json`` (``{split: [scene names]}``) when present,
else the official v1.0-mini split (``MINI_TRAIN_SCENES`` -> ``train``, ``MINI_VAL_SCENES`` ->
``val``). Scenes listed nowhere go to ``train`` with a warning, or raise when ``strict``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from renderworld.constants import MINI_TRAIN_SCENES, MINI_VAL_SCENES
from renderworld.data import DatasetError

__all__ = ["DEFAULT_SPLIT", "load_split_lists", "assign_splits"]

log = logging.getLogger(__name__)
DEFAULT_SPLIT = "train"


def load_split_lists(version_dir: str | Path) -> dict[str, list[str]]:
    """The split lists of a dataset: its ``splits.json`` or the official mini split.

    Raises:
        DatasetError: naming ``splits.json`` if it is not ``{str: [str, ...]}`` or lists a scene
            under two splits.
    """
    path = Path(version_dir) / "splits.json"
    if not path.is_file():
        return {"train": list(MINI_TRAIN_SCENES), "val": list(MINI_VAL_SCENES)}
    try:
        data = json.loads(path.read_text())
    except ValueError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    ok = isinstance(data, dict) and all(
        isinstance(k, str) and isinstance(v, list) and all(isinstance(s, str) for s in v)
        for k, v in data.items()
    )
    if not ok:
        raise DatasetError(f"{path}: expected {{split_name: [scene names]}}")
    seen: dict[str, str] = {}
    for split, names in data.items():
        for name in names:
            if name in seen and seen[name] != split:
                raise DatasetError(
                    f"{path}: scene {name!r} is listed in both {seen[name]!r} and {split!r}"
                )
            seen[name] = split
    return data


def assign_splits(
    scene_names: list[str], version_dir: str | Path, strict: bool = False
) -> dict[str, str]:
    """Map each scene name to its split.

    Args:
        scene_names: the dataset's scenes.
        version_dir: ``<dataroot>/<version>`` (looked in for ``splits.json``).
        strict: raise instead of defaulting unlisted scenes to ``train``.

    Returns:
        {scene name: split name}.

    Raises:
        DatasetError: when ``strict`` and a scene is in no split (naming the scenes and source).
    """
    lists = load_split_lists(version_dir)
    by_scene = {name: split for split, names in lists.items() for name in names}
    unlisted = [s for s in scene_names if s not in by_scene]
    if unlisted:
        source = Path(version_dir) / "splits.json"
        source_txt = str(source) if source.is_file() else "the official v1.0-mini split"
        if strict:
            raise DatasetError(
                f"{len(unlisted)} scene(s) are in no split of {source_txt}: {unlisted[:10]}"
            )
        log.warning(
            "%d scene(s) are in no split of %s; assigning them to %r: %s",
            len(unlisted),
            source_txt,
            DEFAULT_SPLIT,
            unlisted[:10],
        )
    return {s: by_scene.get(s, DEFAULT_SPLIT) for s in scene_names}
