"""The dataset writer: a background writer thread writes the same bytes and reports failures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from renderworld.sim import writer as writer_module
from renderworld.sim.writer import DatasetWriter

VERSION = "v1.0-test"


def _write_some(w: DatasetWriter, n: int) -> None:
    rng = np.random.default_rng(0)
    for i in range(n):
        img = rng.integers(0, 255, (36, 64, 3), dtype=np.uint8)
        w.write_jpeg(f"samples/CAM_FRONT/{i}.jpg", img)
        img[:] = 0  # the caller may reuse its buffer as soon as the call returns
        w.write_points(f"samples/LIDAR_TOP/{i}.pcd.bin", rng.normal(size=(50, 5)))
        sem = rng.integers(0, 18, (20, 20, 4), dtype=np.uint8)
        w.write_occ3d("scene-0000", f"{i:032x}", sem, sem > 3, sem > 9)
        sem[:] = 200
    w.finish()


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def test_background_writer_writes_the_same_bytes(tmp_path, monkeypatch):
    monkeypatch.setattr(writer_module, "MAX_PENDING", 4)  # exercise the bounded queue
    serial = DatasetWriter(tmp_path / "serial", VERSION, 0)
    threaded = DatasetWriter(tmp_path / "threaded", VERSION, 0, background=True)
    _write_some(serial, 12)
    _write_some(threaded, 12)
    a, b = _files(tmp_path / "serial"), _files(tmp_path / "threaded")
    assert len(a) == 36 + len(serial.tables) and a == b
    assert (
        (threaded.files, threaded.bytes)
        == (serial.files, serial.bytes)
        == (
            len(a),
            sum(len(v) for v in a.values()),
        )
    )
    with np.load(tmp_path / "threaded" / "gts/scene-0000" / f"{0:032x}" / "labels.npz") as z:
        assert z["semantics"].max() < 18 and sorted(z.files) == [
            "mask_camera",
            "mask_lidar",
            "semantics",
        ]


def test_a_failed_background_write_is_raised_by_finish(tmp_path):
    (tmp_path / "root").write_text("a file where the dataset root should be")
    w = DatasetWriter(tmp_path / "root", VERSION, 0, background=True)
    w.write_points("samples/LIDAR_TOP/0.pcd.bin", np.zeros((3, 5)))  # fails on the thread
    with pytest.raises(OSError):
        w.finish()
    assert w._pool is None  # closed: nothing more is written
