"""Fixtures of the viewer tests: the converted tiny fixture and small untrained models.

Untrained weights are enough here: the tests check what reaches the recording (entities,
instance counts, timelines), not what the models predict.
"""

from __future__ import annotations

import pytest
import torch

from data_converters import ConvertOptions, create_data
from tests.training.conftest import _single_thread  # noqa: F401 (one torch thread per test)


@pytest.fixture(scope="session")
def converted(tiny_dataset, tmp_path_factory):
    """(data_root, infos_dir) of the tiny fixture converted by the package's converter."""
    out = tmp_path_factory.mktemp("viewer_infos")
    create_data(tiny_dataset, "v1.0-mini", out=out, options=ConvertOptions(progress=False))
    return tiny_dataset, out


@pytest.fixture(scope="session")
def tiny_models():
    """(Img2Occ, tokenizer, planner) on the coarse 50x50x4 grid, tiny and untrained."""
    from renderworld.constants import GRIDS
    from renderworld.img2occ import Img2Occ, Img2OccConfig
    from renderworld.planning import Planner
    from renderworld.tokenizer import TokenizerConfig, build_tokenizer
    from renderworld.world import WorldModel, WorldModelConfig

    torch.manual_seed(0)
    img2occ = Img2Occ(
        Img2OccConfig(
            grid=GRIDS["coarse"], input_size=(48, 88), render_size=(18, 32),
            encoder_channels=(8, 16, 16), feature_channels=16, head_channels=32, head_blocks=1,
        )
    ).eval()  # fmt: skip
    tok = build_tokenizer(
        TokenizerConfig(grid_shape=(50, 50, 4), latent_shape=(25, 25), latent_channels=8,
                        codebook_size=16, base_channels=8, num_res_blocks=1, attention=False)
    ).eval()  # fmt: skip
    wm = WorldModel(
        WorldModelConfig(codebook_sizes=tuple(tok.cfg.codebook_sizes), token_grid=(25, 25),
                         embed_dim=16, num_heads=2, num_scales=1, layers_per_scale=(1,))
    )  # fmt: skip
    return img2occ, tok, Planner(tok, wm)
