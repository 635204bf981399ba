"""Shared fixtures: one synthetic sample (ray casting is the slow part) and a tiny config."""

from __future__ import annotations

import pytest
import torch

from renderworld.img2occ import Img2OccConfig
from tests.img2occ._synthetic import TEST_GRID, make_sample

INPUT_SIZE = (48, 88)
RENDER_SIZE = (18, 32)


def make_model(backend: str = "torch", **overrides):
    """A tiny Img2Occ rendering with ``renderworld.splat.rasterize(backend=...)``, or with
    the tests' dense stand-in when ``backend == "dense"``."""
    from renderworld.img2occ import Img2Occ
    from tests.img2occ._dense_render import dense_rasterize

    if backend == "dense":
        return Img2Occ(tiny_config(**overrides), render_fn=dense_rasterize)
    return Img2Occ(tiny_config(render_backend=backend, **overrides))


def tiny_config(**overrides) -> Img2OccConfig:
    """A model small enough for CPU unit tests on the 16x16x4 test grid."""
    kw = dict(
        grid=TEST_GRID,
        input_size=INPUT_SIZE,
        render_size=RENDER_SIZE,
        encoder_channels=(8, 16, 16),
        feature_channels=16,
        head_channels=32,
        head_blocks=1,
        views_per_step=3,
    )
    kw.update(overrides)
    return Img2OccConfig(**kw)


@pytest.fixture(scope="session")
def synthetic_batch() -> dict:
    """B = 1 batch of the synthetic scene seen by the six nuScenes cameras."""
    return make_sample(input_size=INPUT_SIZE, render_size=RENDER_SIZE)


@pytest.fixture(autouse=True)
def _seed_and_one_thread():
    # Tensors here are tiny: intra-op threads only add OpenMP overhead, which becomes
    # severe when the CPU is shared (measured 10x slower steps with 2 threads under load).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    yield
    torch.set_num_threads(threads)
