import pytest


@pytest.fixture(autouse=True)
def _isolated_table_cache(tmp_path, monkeypatch):
    """Each test gets its own table cache (never the user's ~/.cache)."""
    monkeypatch.setenv("RENDERWORLD_CACHE_DIR", str(tmp_path / "table-cache"))
