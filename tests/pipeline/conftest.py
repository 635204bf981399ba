"""Config composition and the one-thread pin shared with the training tests."""

from tests.training.conftest import _single_thread, compose_cfg  # noqa: F401
