"""A parquet cache of validated nuScenes tables, so a dataset is parsed and checked once.

Key: the absolute version folder and the (name, size, mtime) of every JSON table in it, plus
a schema version. Any change to any table invalidates the whole cache of that version (so
cross-table reference checks stay valid). Tables are written only after they passed their
checks, atomically (temp file + rename); a failure to write only warns.

Location: ``$RENDERWORLD_CACHE_DIR`` or ``~/.cache/renderworld``, under ``tables/``.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from renderworld.cache import cache_root

__all__ = ["TableCache", "default_cache_root"]

CACHE_SCHEMA = 1


def default_cache_root() -> Path:
    """The package's cache root: ``$RENDERWORLD_CACHE_DIR`` or ``~/.cache/renderworld``."""
    return cache_root()


class TableCache:
    """Cached, validated tables of one ``<dataroot>/<version>`` folder.

    Args:
        version_dir: the dataset's version folder.
        root: cache root (default :func:`default_cache_root`).
    """

    def __init__(self, version_dir: Path, root: Path | None = None):
        version_dir = Path(version_dir).resolve()
        sig = hashlib.sha1(f"{CACHE_SCHEMA}|{version_dir}".encode())
        for p in sorted(version_dir.glob("*.json")):
            st = p.stat()
            sig.update(f"|{p.name}|{st.st_size}|{st.st_mtime_ns}".encode())
        where = hashlib.sha1(str(version_dir).encode()).hexdigest()[:12]
        self.dir = (root or default_cache_root()) / "tables" / where / sig.hexdigest()[:16]

    def get(self, name: str) -> pd.DataFrame | None:
        """The cached table, or None if absent or unreadable."""
        path = self.dir / f"{name}.parquet"
        if not path.is_file():
            return None
        try:
            table = pq.read_table(path)
        except (OSError, pa.ArrowException):
            return None
        cols = {}
        for field in table.schema:
            col = table.column(field.name)
            if pa.types.is_string(field.type) or pa.types.is_large_string(field.type):
                cols[field.name] = pd.Series(col.to_numpy(zero_copy_only=False), dtype=object)
            elif pa.types.is_list(field.type):
                cols[field.name] = pd.Series(pd.arrays.ArrowExtensionArray(col))
            else:
                cols[field.name] = pd.Series(col.to_numpy())
        df = pd.DataFrame(cols, copy=False)
        df.index = pd.Index(df["token"].to_numpy(), dtype=object) if len(df) else pd.Index([])
        return df

    def put(self, name: str, df: pd.DataFrame) -> None:
        """Store a validated table (best effort: warns and carries on when it cannot)."""
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            tmp = self.dir / f".{name}.{os.getpid()}.tmp"
            pq.write_table(pa.Table.from_pandas(df, preserve_index=False), tmp)
            os.replace(tmp, self.dir / f"{name}.parquet")
        except (OSError, pa.ArrowException) as exc:
            warnings.warn(f"table cache: could not write {name} to {self.dir}: {exc}", stacklevel=2)
