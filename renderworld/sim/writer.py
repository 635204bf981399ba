"""nuScenes-format writer: the 13 tables + lidarseg, sensor files, maps and Occ3D gts.

Tokens are 32-hex strings hashed from the seed and a record key, so a seed fixes every byte.
Files are written deterministically: sorted-key JSON, PIL JPEG at a fixed quality, ``.npz``
zips with a fixed member timestamp. With ``background=True`` the files are encoded (JPEG, zlib)
and written on one writer thread while the caller goes on simulating (zlib, PIL and file I/O
release the GIL, so the two overlap on two cores); the bytes written are the same.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
from PIL import Image

from renderworld.constants import LIDARSEG_CLASSES, NUSCENES_TABLES

__all__ = ["DatasetWriter", "make_token", "write_npz", "ATTRIBUTES", "VISIBILITIES"]

ATTRIBUTES = (
    ("vehicle.moving", "Vehicle is moving."),
    ("vehicle.stopped", "Vehicle, with a driver/rider in/on it, is currently stationary."),
    ("vehicle.parked", "Vehicle is stationary (usually for longer duration) with no driver."),
    ("cycle.with_rider", "There is a rider on the bicycle or motorcycle."),
    ("cycle.without_rider", "There is NO rider on the bicycle or motorcycle."),
    ("pedestrian.sitting_lying_down", "The human is sitting or lying down."),
    ("pedestrian.standing", "The human is standing."),
    ("pedestrian.moving", "The human is moving."),
)
VISIBILITIES = (
    ("1", "v0-40", "visibility of whole object is between 0 and 40%"),
    ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
    ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
    ("4", "v80-100", "visibility of whole object is between 80 and 100%"),
)
#: Files a background writer may hold queued before the caller waits for it (bounds memory).
MAX_PENDING = 32


def make_token(seed: int, *key) -> str:
    """Deterministic 32-hex token of ``seed`` and a record key."""
    return hashlib.md5(("/".join(str(k) for k in (seed, *key))).encode()).hexdigest()


def write_npz(path: Path | io.BytesIO, **arrays: np.ndarray) -> None:
    """``np.savez_compressed``-compatible file (a path or a binary buffer) with fixed zip
    timestamps (byte-reproducible)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, buf.getvalue())


class DatasetWriter:
    """Accumulates table records and writes files under ``root``.

    Args:
        root: dataset root (the directory that will hold ``<version>/``, ``samples/``, ...).
        version: e.g. ``"v1.0-mini"``.
        seed: token seed.
        jpeg_quality: JPEG quality.
        lidarseg: write the ``lidarseg`` table (False: no ``lidarseg.json``, as a nuScenes
            dataset without the lidarseg extension).
        background: encode and write files on one writer thread; :meth:`finish` waits for it
            and raises what it raised; :meth:`close` stops it (call it when giving up).
    """

    def __init__(
        self,
        root: Path,
        version: str,
        seed: int,
        jpeg_quality: int = 90,
        lidarseg: bool = True,
        background: bool = False,
    ):
        self.root, self.version, self.seed, self.q = Path(root), version, seed, jpeg_quality
        self._pool = (
            ThreadPoolExecutor(1, thread_name_prefix="dataset-writer") if background else None
        )
        self._pending: deque[Future] = deque()
        self.tables: dict[str, list[dict]] = {t: [] for t in NUSCENES_TABLES}
        if lidarseg:
            self.tables["lidarseg"] = []
        self.bytes = 0
        self.files = 0
        for i, name in enumerate(LIDARSEG_CLASSES):
            self.add("category", self.tok("category", name), name=name, index=i,
                     description=f"{name} (simulated)")  # fmt: skip
        for name, desc in ATTRIBUTES:
            self.add("attribute", self.tok("attribute", name), name=name, description=desc)
        for token, level, desc in VISIBILITIES:
            self.add("visibility", token, level=level, description=desc)

    def tok(self, *key) -> str:
        """Token of a record key."""
        return make_token(self.seed, *key)

    def add(self, table: str, token: str, **fields) -> dict:
        """Append a record to ``table``; returns it (mutable until :meth:`finish`)."""
        rec = {"token": token, **fields}
        self.tables[table].append(rec)
        return rec

    # ------------------------------------------------------------------ files
    def _submit(self, path: Path, encode: Callable[[], bytes]) -> None:
        """Write ``encode()`` (the file's bytes) to ``path``, on the writer thread if any."""

        def job() -> int:
            data = encode()
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
            return len(data)

        if self._pool is None:
            self._count(job())
            return
        self._pending.append(self._pool.submit(job))
        if len(self._pending) > MAX_PENDING:
            self._drain(MAX_PENDING // 2)

    def _count(self, size: int) -> None:
        self.bytes += size
        self.files += 1

    def _drain(self, keep: int = 0) -> None:
        """Wait until at most ``keep`` files are queued; re-raise a failed write."""
        while len(self._pending) > keep:
            self._count(self._pending.popleft().result())

    def _write(self, rel: str, data: bytes) -> str:
        self._submit(self.root / rel, lambda: data)
        return rel

    def write_jpeg(self, rel: str, img: np.ndarray) -> str:
        """Write a uint8 image [H, W, 3] as JPEG at ``rel``."""
        img = np.array(img, copy=True)

        def encode() -> bytes:
            buf = io.BytesIO()
            Image.fromarray(img).save(buf, format="JPEG", quality=self.q)
            return buf.getvalue()

        self._submit(self.root / rel, encode)
        return rel

    def write_points(self, rel: str, points: np.ndarray) -> str:
        """Write [N, 5] float32 points as a headerless little-endian ``.pcd.bin``."""
        return self._write(rel, np.ascontiguousarray(points, dtype="<f4").tobytes())

    def write_lidarseg(self, sd_token: str, labels: np.ndarray) -> str:
        """Write uint8 labels [N] for LiDAR sample_data ``sd_token``; adds the lidarseg record."""
        if "lidarseg" not in self.tables:
            raise ValueError("lidarseg: this writer was made with lidarseg=False")
        rel = f"lidarseg/{self.version}/{sd_token}_lidarseg.bin"
        self._write(rel, np.asarray(labels, dtype=np.uint8).tobytes())
        self.add("lidarseg", sd_token, sample_data_token=sd_token, filename=rel)
        return rel

    def write_occ3d(self, scene_name: str, sample_token: str, sem, mask_lidar, mask_camera) -> str:
        """Write ``gts/<scene>/<sample>/labels.npz`` (semantics, mask_lidar, mask_camera)."""
        rel = f"gts/{scene_name}/{sample_token}/labels.npz"
        arrays = {
            k: np.array(v, copy=True)
            for k, v in (
                ("semantics", sem),
                ("mask_lidar", mask_lidar),
                ("mask_camera", mask_camera),
            )
        }

        def encode() -> bytes:
            buf = io.BytesIO()
            write_npz(buf, **arrays)
            return buf.getvalue()

        self._submit(self.root / rel, encode)
        return rel

    def write_map(self, token: str, raster: np.ndarray) -> str:
        """Write a grayscale map PNG (uint8 [H, W]) for map ``token``."""
        buf = io.BytesIO()
        Image.fromarray(raster).save(buf, format="PNG")
        return self._write(f"maps/{token}.png", buf.getvalue())

    def finish(self) -> None:
        """Write every table as sorted-key JSON under ``<root>/<version>/``; wait for every file.

        Raises:
            Exception: whatever a background write raised (the writer is closed first).
        """
        for name, records in self.tables.items():
            data = json.dumps(records, indent=1, sort_keys=True).encode()
            self._write(f"{self.version}/{name}.json", data)
        try:
            self._drain()
        finally:
            self.close()

    def close(self) -> None:
        """Stop the writer thread: queued files not yet started are dropped, a running one ends."""
        if self._pool is not None:
            for f in self._pending:
                f.cancel()
            self._pool.shutdown(wait=True)
            self._pool = None
        self._pending.clear()


def link_chain(records: list[dict]) -> None:
    """Fill ``prev``/``next`` of records in order ("" at the ends)."""
    for i, rec in enumerate(records):
        rec["prev"] = records[i - 1]["token"] if i > 0 else ""
        rec["next"] = records[i + 1]["token"] if i + 1 < len(records) else ""
