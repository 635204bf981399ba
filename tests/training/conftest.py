"""Shared helpers for the training tests: compose configs with the test stage on the path."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"
TEST_CONFIGS = Path(__file__).resolve().parent / "configs"
SEARCHPATH = f"hydra.searchpath=[file://{TEST_CONFIGS}]"


def compose_cfg(
    overrides: Sequence[str] = (), config_name: str = "train", hydra_cfg: bool = False
) -> DictConfig:
    """Compose ``configs/<config_name>.yaml`` with the tests' config dir on the search path."""
    with initialize_config_dir(str(CONFIGS), version_base="1.3"):
        return compose(
            config_name, overrides=[SEARCHPATH, *overrides], return_hydra_config=hydra_cfg
        )


def fit_cfg(run_dir: Path, *overrides: str) -> DictConfig:
    """The regression experiment (tests/training/configs) writing into ``run_dir``."""
    return compose_cfg(["experiment=regression_fit", f"run_dir={run_dir}", *overrides])


def subprocess_env() -> dict[str, str]:
    """Environment for tool subprocesses: single-threaded, no inherited torchrun variables."""
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env["OMP_NUM_THREADS"] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    return env


def params_of(path: Path) -> dict[str, torch.Tensor]:
    """Model parameters stored in a checkpoint."""
    return torch.load(path, map_location="cpu", weights_only=True)["model"]


@pytest.fixture(autouse=True)
def _single_thread():
    """Tests compare runs bit for bit: pin torch's thread count for the duration."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


PYTHON = sys.executable
