from tests.converter.conftest import left_turn  # noqa: F401  (shared session fixture)
