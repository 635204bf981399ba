"""Loading nuScenes JSON tables into pandas DataFrames, with schema and reference checks.

Each table ``<dataroot>/<version>/<name>.json`` is a JSON list of records. Tables become
DataFrames indexed by ``token`` (lidarseg: also by token; its ``sample_data_token`` is a column).
Parsing uses orjson (several times faster than the standard library on trainval-sized tables).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import orjson
import pandas as pd

from renderworld.data.errors import DatasetError

__all__ = ["TABLE_FIELDS", "read_table", "check_references", "check_chain"]

#: Fields every record of each table must have (FACTS.md).
TABLE_FIELDS: dict[str, tuple[str, ...]] = {
    "attribute": ("token", "name", "description"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation", "camera_intrinsic"),
    "category": ("token", "name", "description"),
    "ego_pose": ("token", "translation", "rotation", "timestamp"),
    "instance": (
        "token",
        "category_token",
        "nbr_annotations",
        "first_annotation_token",
        "last_annotation_token",
    ),
    "log": ("token", "logfile", "vehicle", "date_captured", "location"),
    "map": ("token", "log_tokens", "category", "filename"),
    "sample": ("token", "timestamp", "scene_token", "prev", "next"),
    "sample_annotation": (
        "token",
        "sample_token",
        "instance_token",
        "attribute_tokens",
        "visibility_token",
        "translation",
        "size",
        "rotation",
        "num_lidar_pts",
        "num_radar_pts",
        "prev",
        "next",
    ),
    "sample_data": (
        "token",
        "sample_token",
        "ego_pose_token",
        "calibrated_sensor_token",
        "filename",
        "fileformat",
        "width",
        "height",
        "timestamp",
        "is_key_frame",
        "prev",
        "next",
    ),
    "scene": (
        "token",
        "name",
        "description",
        "log_token",
        "nbr_samples",
        "first_sample_token",
        "last_sample_token",
    ),
    "sensor": ("token", "channel", "modality"),
    "visibility": ("token", "level", "description"),
    "lidarseg": ("token", "sample_data_token", "filename"),
}


def read_table(version_dir: Path, name: str) -> pd.DataFrame:
    """Read ``<version_dir>/<name>.json`` into a DataFrame indexed by ``token``.

    Args:
        version_dir: the ``<dataroot>/<version>`` folder.
        name: table name (a key of :data:`TABLE_FIELDS`).

    Returns:
        DataFrame with one row per record, index ``token`` (unique), the schema's fields as
        columns (extra fields kept).

    Raises:
        DatasetError: naming the file when it is missing, not JSON, not a list of objects,
            lacks a field, or repeats a token.
    """
    path = Path(version_dir) / f"{name}.json"
    if not path.is_file():
        raise DatasetError(f"{path}: table {name!r} is missing")
    try:
        records = orjson.loads(path.read_bytes())
    except orjson.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(records, list):
        raise DatasetError(f"{path}: expected a JSON list of records, got {type(records).__name__}")
    fields = TABLE_FIELDS[name]
    columns: dict[str, list] = {}
    try:
        for field in fields:
            columns[field] = [r[field] for r in records]
    except KeyError:
        bad = next(i for i, r in enumerate(records) if field not in r)
        token = records[bad].get("token", "?")
        raise DatasetError(
            f"{path}: record {bad} (token {token!r}) lacks field {field!r}"
        ) from None
    except TypeError:
        bad = next(i for i, r in enumerate(records) if not isinstance(r, dict))
        raise DatasetError(f"{path}: record {bad} is not a JSON object") from None
    if records:
        extra = [k for k in records[0] if k not in columns]
        for k in extra:
            columns[k] = [r.get(k) for r in records]
    df = pd.DataFrame(columns)
    df = df.set_index("token", drop=False)
    df.index.name = None
    if not df.index.is_unique:
        dup = df.index[df.index.duplicated()][0]
        raise DatasetError(f"{path}: token {dup!r} appears more than once")
    return df


def check_references(
    child: pd.DataFrame,
    child_name: str,
    column: str,
    parent_index: pd.Index,
    parent_name: str,
    allow_empty: bool = False,
) -> None:
    """Raise if any ``child[column]`` token is not in ``parent_index``.

    Raises:
        DatasetError: naming the child table, the record's token, the column and the value.
    """
    values = child[column]
    bad = ~values.isin(parent_index)
    if allow_empty:
        bad &= values != ""
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        raise DatasetError(
            f"{child_name}.json: record {child.index[i]!r} has {column}={values.iloc[i]!r}, "
            f"which is not a token of {parent_name}.json ({int(bad.sum())} dangling in all)"
        )


def check_chain(df: pd.DataFrame, name: str) -> None:
    """Check ``prev``/``next`` links: each names an existing record or is ``""``, and agree.

    Raises:
        DatasetError: naming the table and the record whose link is broken.
    """
    check_references(df, name, "prev", df.index, name, allow_empty=True)
    check_references(df, name, "next", df.index, name, allow_empty=True)
    nxt = df["next"]
    has_next = (nxt != "").to_numpy()
    if has_next.any():
        src = df.index.to_numpy()[has_next]
        dst = nxt.to_numpy()[has_next]
        back = df["prev"].reindex(dst).to_numpy()
        bad = back != src
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DatasetError(
                f"{name}.json: broken prev/next chain: record {src[i]!r} has next={dst[i]!r} "
                f"but that record has prev={back[i]!r}"
            )
