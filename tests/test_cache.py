"""One setting moves every on-disk cache: ``RENDERWORLD_CACHE_DIR`` (the old name warns)."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from renderworld.cache import cache_root
from renderworld.data.table_cache import TableCache
from renderworld.splat import cpp_backend
from renderworld.training.stages.world_model.settings import frame_cache_dir


def _caches(version_dir: Path) -> dict[str, Path]:
    """Where the reader's tables, the frame cache and the compiled rasterizer go now."""
    frames = frame_cache_dir(OmegaConf.create({"stage": {"frame_cache": True}}))
    return {
        "tables": TableCache(version_dir).dir,
        "frames": frames,
        "splat_ext": cpp_backend._cache_root(),
    }


def test_one_variable_moves_every_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("RENDERWORLD_CACHE_DIR", str(tmp_path / "here"))
    monkeypatch.setenv("RENDERWORLD_CACHE", str(tmp_path / "old"))  # ignored beside the new one
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        where = _caches(tmp_path)
    for name, path in where.items():
        assert path.is_relative_to(tmp_path / "here" / name), (name, path)
    monkeypatch.delenv("RENDERWORLD_CACHE_DIR")
    monkeypatch.delenv("RENDERWORLD_CACHE")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for name, path in _caches(tmp_path).items():
        assert path.is_relative_to(tmp_path / "home" / ".cache" / "renderworld" / name), name


def test_the_old_name_still_works_with_a_deprecation_warning(monkeypatch, tmp_path):
    monkeypatch.delenv("RENDERWORLD_CACHE_DIR", raising=False)
    monkeypatch.setenv("RENDERWORLD_CACHE", str(tmp_path / "old"))
    with pytest.warns(DeprecationWarning, match=r"\$RENDERWORLD_CACHE is deprecated: set "):
        where = _caches(tmp_path)
    for name, path in where.items():
        assert path.is_relative_to(tmp_path / "old" / name), (name, path)
    monkeypatch.setenv("RENDERWORLD_CACHE", "")  # empty: unset
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert cache_root() == tmp_path / "home" / ".cache" / "renderworld"
