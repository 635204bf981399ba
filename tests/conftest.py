"""Shared session fixtures: simulated nuScenes-format datasets.

``tiny_dataset`` (session scope) -> ``pathlib.Path`` of a dataset root made by the simulator
with ``configs/sim/preset/tiny.yaml``: version ``v1.0-mini``, 2 scenes (``scene-0061`` from
mini_train, ``scene-0103`` from mini_val) x 8 keyframes, 192x108 JPEGs for the six cameras,
LIDAR_TOP ``.pcd.bin`` (x, y, z, intensity, ring) with lidarseg labels (32 official classes),
Occ3D ``gts/<scene>/<sample>/labels.npz`` (semantics, mask_lidar, mask_camera) and
``sim_report.json``. The root holds ``v1.0-mini/*.json`` (13 tables + lidarseg.json),
``samples/``, ``lidarseg/``, ``maps/``, ``gts/``. It is read-only by contract: tests must not
modify it (copy it to ``tmp_path`` first).

It is cached under ``<repo>/.cache/fixtures/tiny-<hash>``, the hash covering the simulator's
code and the preset, so repeated runs reuse it and a code change regenerates it. The dataset is
written to a temporary directory and renamed into place, and generation is file-locked, so
parallel or interrupted sessions never see a half-written fixture.

``mini_dataset`` (session scope, for ``slow`` tests and demos): the same with the ``mini``
preset (10 official mini scene names x 24 keyframes, 400x225 images; ~2-3 minutes once).
"""

from __future__ import annotations

import fcntl
import hashlib
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
FIXTURE_CACHE = REPO_ROOT / ".cache" / "fixtures"
_HASHED = (
    "renderworld/sim",
    "renderworld/geometry",
    "renderworld/constants.py",
    "configs/sim",
    "tools/make_fixtures.py",
)


def fixture_hash(preset: str, **overrides) -> str:
    """Hash of the simulator code, its configs, and the preset name + overrides.

    Of ``configs/sim/preset/`` only this preset's file counts: adding a preset leaves the
    other fixtures' caches valid.
    """
    h = hashlib.sha256(f"{preset}:{sorted(overrides.items())}".encode())
    presets = REPO_ROOT / "configs" / "sim" / "preset"
    for rel in _HASHED:
        p = REPO_ROOT / rel
        files = sorted(p.rglob("*")) if p.is_dir() else [p]
        for f in files:
            if f.parent == presets and f.stem != preset:
                continue
            if f.is_file() and f.suffix in (".py", ".yaml"):
                h.update(str(f.relative_to(REPO_ROOT)).encode())
                h.update(f.read_bytes())
    return h.hexdigest()[:16]


def make_fixture(preset: str = "tiny", **overrides) -> Path:
    """Generate (once, cached, file-locked) the dataset of ``preset``; returns its root."""
    from renderworld.sim import simulate
    from tools.make_fixtures import config_from_preset

    root = FIXTURE_CACHE / f"{preset}-{fixture_hash(preset, **overrides)}"
    if root.exists():
        return root
    FIXTURE_CACHE.mkdir(parents=True, exist_ok=True)
    with open(FIXTURE_CACHE / f".{preset}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not root.exists():
            simulate(config_from_preset(preset, **overrides), root, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_dataset() -> Path:
    """Root of the cached ``tiny`` simulated dataset (see module docstring)."""
    return make_fixture("tiny")


@pytest.fixture(scope="session")
def full_dataset() -> Path:
    """Root of the cached ``full`` simulated dataset: Occ3D grid, 800x450 images, laid out as
    v1.0-trainval (slow-marked tests only; see configs/sim/preset/full.yaml)."""
    return make_fixture("full")


@pytest.fixture(scope="session")
def mini_dataset() -> Path:
    """Root of the cached ``mini`` simulated dataset (slow to build the first time)."""
    return make_fixture("mini")


@pytest.fixture(autouse=True, scope="session")
def _isolated_table_cache(tmp_path_factory):
    """Tests never write the package's caches into the user's ~/.cache.

    The cache root is a fresh folder per session (tables and frames start empty); only the
    compiled C++ rasterizer (``splat_ext/``, keyed by source, flags and torch) is kept across
    sessions, under ``<repo>/.cache``.
    """
    import os

    old = os.environ.get("RENDERWORLD_CACHE_DIR")
    root = tmp_path_factory.mktemp("cache-root")
    kernels = REPO_ROOT / ".cache" / "splat_ext"
    kernels.mkdir(parents=True, exist_ok=True)
    (root / "splat_ext").symlink_to(kernels, target_is_directory=True)
    os.environ["RENDERWORLD_CACHE_DIR"] = str(root)
    yield
    if old is None:
        os.environ.pop("RENDERWORLD_CACHE_DIR", None)
    else:
        os.environ["RENDERWORLD_CACHE_DIR"] = old
