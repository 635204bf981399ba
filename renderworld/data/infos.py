"""Per-keyframe infos: the columnar (parquet) table written by ``tools/create_data.py``.

One row per keyframe, one file per split (``<out>/infos_<split>.parquet``); the columns are those
of docs/formats.md#infos. Numeric arrays are fixed-size float64 list columns (matrices row-major),
masks fixed-size bool lists, ``future_boxes`` a nested list (7 frames x boxes x 7 numbers
``[x, y, length, width, yaw, occ3d_class, instance]`` in the keyframe's ego frame; ``instance``
is the road user's index, the same in every frame). Never pickles.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from renderworld.constants import CAMERA_NAMES, FUTURE_FRAMES
from renderworld.data.atomic import atomic_write
from renderworld.data.errors import DatasetError

__all__ = [
    "ALL_SPLITS",
    "INFOS_SCHEMA_VERSION",
    "HISTORY_STEPS",
    "BOX_FIELDS",
    "infos_schema",
    "write_infos",
    "load_infos",
    "stack_column",
    "infos_file",
]

INFOS_SCHEMA_VERSION = 2
#: Split name that :func:`load_infos` reads as every split of a folder (never a file's name).
ALL_SPLITS = "all"
#: Past per-step displacements stored per keyframe (frames t-3..t).
HISTORY_STEPS = 4
#: Numbers per stored box, in this order (current ego frame; metres, rad, Occ3D id).
BOX_FIELDS = ("x", "y", "length", "width", "yaw", "occ3d_class", "instance")
_META_KEY = b"renderworld"


def _f64(n: int) -> pa.DataType:
    return pa.list_(pa.float64(), n)


def infos_schema() -> pa.Schema:
    """The arrow schema of an infos file (column order of docs/formats.md#infos)."""
    fields = [
        ("scene_name", pa.string()),
        ("scene_description", pa.string()),
        ("scene_index", pa.int32()),
        ("frame_index", pa.int32()),
        ("sample_token", pa.string()),
        ("timestamp", pa.int64()),
        ("split", pa.string()),
    ]
    for c in range(len(CAMERA_NAMES)):
        fields += [
            (f"cam{c}_path", pa.string()),
            (f"cam{c}_intrinsics", _f64(9)),
            (f"cam{c}_width", pa.int32()),
            (f"cam{c}_height", pa.int32()),
            (f"cam{c}_sensor2ego", _f64(16)),
            (f"cam{c}_ego2global", _f64(16)),
            (f"cam{c}_timestamp", pa.int64()),
        ]
    fields += [
        ("lidar_token", pa.string()),
        ("lidar_path", pa.string()),
        ("lidar2ego", _f64(16)),
        ("ego2global", _f64(16)),
        ("occ_path", pa.string()),
        ("labels2d_path", pa.string()),
        ("ego_history", _f64(2 * HISTORY_STEPS)),
        ("ego_history_mask", pa.list_(pa.bool_(), HISTORY_STEPS)),
        ("ego_future", _f64(2 * FUTURE_FRAMES)),
        ("ego_future_mask", pa.list_(pa.bool_(), FUTURE_FRAMES)),
        ("command", pa.string()),
        (
            "future_boxes",
            pa.list_(pa.list_(_f64(len(BOX_FIELDS))), FUTURE_FRAMES + 1),
        ),
    ]
    return pa.schema(fields)


def infos_file(out_dir: str | os.PathLike, split: str) -> Path:
    """``<out_dir>/infos_<split>.parquet``."""
    return Path(out_dir) / f"infos_{split}.parquet"


def write_infos(
    rows: list[dict] | pd.DataFrame, path: str | os.PathLike, metadata: dict | None = None
) -> Path:
    """Write infos rows to parquet atomically (temp file + rename).

    Args:
        rows: list of dicts (or a DataFrame) with exactly the schema's columns.
        path: destination ``.parquet``.
        metadata: JSON-serialisable dict stored in the file's schema metadata.

    Returns:
        The written path.
    """
    schema = infos_schema()
    if isinstance(rows, pd.DataFrame):
        rows = rows.to_dict("records")
    if rows:
        missing = [n for n in schema.names if n not in rows[0]]
        extra = [n for n in rows[0] if n not in schema.names]
        if missing or extra:
            raise ValueError(f"rows: expected the infos columns; missing {missing}, extra {extra}")
    columns = {
        n: pa.array([_plain(r[n]) for r in rows], type=schema.field(n).type) for n in schema.names
    }
    meta = {"schema_version": INFOS_SCHEMA_VERSION, **(metadata or {})}
    table = pa.table(columns, schema=schema.with_metadata({_META_KEY: json.dumps(meta)}))
    return atomic_write(path, lambda tmp: pq.write_table(table, tmp))


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def load_infos(path: str | os.PathLike, split: str | None = None) -> pd.DataFrame:
    """Read an infos parquet file (or ``<dir>/infos_<split>.parquet``, or every split of a folder).

    Args:
        path: a ``.parquet`` file, or the converter's output folder together with ``split``.
        split: split name when ``path`` is a folder; ``"all"`` (:data:`ALL_SPLITS`) reads every
            ``infos_<split>.parquet`` of the folder as one table (e.g. to evaluate every scene
            of a held-out fixture: ``dataset.val_split=all``).

    Returns:
        DataFrame, one row per keyframe, sorted by (scene_index, frame_index). Its ``attrs``
        hold ``infos_dir`` (the file's folder, base of out-relative paths) and ``metadata``;
        with ``"all"`` also ``splits``, the split names read (sorted).

    Raises:
        DatasetError: naming the file if it is missing, unreadable, of another schema version,
            or lacks columns; with ``"all"``, naming the folder if it holds no infos file, and
            the files if their metadata differ or a sample token is in two of them.
    """
    path = Path(path)
    if path.is_dir():
        if split is None:
            raise ValueError(f"split: required when path is a folder ({path})")
        if split == ALL_SPLITS:
            return _load_all_splits(path)
        path = infos_file(path, split)
    return _load_one(path)


def _load_one(path: Path) -> pd.DataFrame:
    """:func:`load_infos` of one file."""
    if not path.is_file():
        raise DatasetError(f"{path}: infos file not found (run tools/create_data.py)")
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise DatasetError(f"{path}: not a readable parquet file ({exc})") from exc
    raw = (table.schema.metadata or {}).get(_META_KEY)
    meta = json.loads(raw) if raw else {}
    if meta.get("schema_version") != INFOS_SCHEMA_VERSION:
        raise DatasetError(
            f"{path}: infos schema version {meta.get('schema_version')!r}, expected "
            f"{INFOS_SCHEMA_VERSION} (re-run tools/create_data.py overwrite=true)"
        )
    missing = [n for n in infos_schema().names if n not in table.column_names]
    if missing:
        raise DatasetError(f"{path}: infos lack column(s) {missing}")
    df = table.to_pandas()
    df = df.sort_values(["scene_index", "frame_index"], kind="stable").reset_index(drop=True)
    df.attrs["infos_dir"] = str(path.parent)
    df.attrs["metadata"] = meta
    return df


def _load_all_splits(folder: Path) -> pd.DataFrame:
    """Every ``infos_<split>.parquet`` of ``folder`` as one table (see :func:`load_infos`)."""
    files = sorted(folder.glob("infos_*.parquet"))
    if not files:
        raise DatasetError(
            f"{folder}: split {ALL_SPLITS!r} found no infos_<split>.parquet file in this folder "
            "(run tools/create_data.py)"
        )
    parts = [_load_one(f) for f in files]
    meta = parts[0].attrs["metadata"]
    for f, part in zip(files[1:], parts[1:]):
        if part.attrs["metadata"] != meta:
            raise DatasetError(
                f"{folder}: split {ALL_SPLITS!r}: {f.name} and {files[0].name} come from "
                f"different conversions (metadata {part.attrs['metadata']} vs {meta})"
            )
    df = pd.concat(parts, ignore_index=True)
    twice = df["sample_token"][df["sample_token"].duplicated()]
    if len(twice):
        raise DatasetError(
            f"{folder}: split {ALL_SPLITS!r}: sample token {twice.iloc[0]!r} is in two infos "
            f"files of {[f.name for f in files]}"
        )
    df = df.sort_values(["scene_index", "frame_index"], kind="stable").reset_index(drop=True)
    df.attrs["infos_dir"] = str(folder)
    df.attrs["metadata"] = meta
    df.attrs["splits"] = [f.name[len("infos_") : -len(".parquet")] for f in files]
    return df


def stack_column(df: pd.DataFrame, column: str, shape: tuple[int, ...], dtype=np.float64):
    """Stack a fixed-size list column into one array.

    Args:
        df: infos DataFrame.
        column: e.g. ``"ego2global"``.
        shape: per-row shape, e.g. ``(4, 4)``.

    Returns:
        [len(df), *shape] array of ``dtype``.
    """
    if column not in df.columns:
        raise ValueError(f"column: {column!r} is not an infos column")
    values = df[column].to_numpy()
    if len(values) == 0:
        return np.zeros((0, *shape), dtype=dtype)
    return np.stack([np.asarray(v, dtype=dtype) for v in values]).reshape(len(df), *shape)
