"""The paper-scale experiments compose into the paper's settings (fast; the slow end-to-end run
on the full-grid preset is tests/training/test_paper_scale.py)."""

from __future__ import annotations

import pytest

from renderworld.training.config import TrainerConfig, validate_group
from renderworld.training.stages.img2occ import img2occ_config
from renderworld.training.stages.tokenizer import tokenizer_config
from renderworld.training.stages.world_model.settings import world_model_config

from .conftest import compose_cfg

PAPER = ["paper_img2occ", "paper_tokenizer", "paper_world_model", "paper_camera"]


@pytest.mark.parametrize("experiment", PAPER)
def test_paper_experiment_is_real_data_at_the_occ3d_grid_on_a_gpu(experiment):
    inputs = ["stage.tokenizer_ckpt=t.pt", "stage.occ_root=x"] if "camera" in experiment else []
    cfg = compose_cfg([f"experiment={experiment}", *inputs])
    assert cfg.dataset.name == "nuscenes" and cfg.dataset.version == "v1.0-trainval"
    assert list(cfg.grid.shape) == [200, 200, 16]
    t = validate_group(cfg.trainer, TrainerConfig, "trainer")
    assert t.device == "cuda" and t.precision == "bf16" and t.max_epochs >= 1


def test_paper_img2occ_is_640k_gaussians_at_nuscenes_input_size():
    cfg = img2occ_config(compose_cfg(["experiment=paper_img2occ"]))
    assert cfg.grid.num_voxels == 640_000
    assert tuple(cfg.input_size) == (256, 704) and tuple(cfg.render_size) == (225, 400)
    assert cfg.views_per_step == 3


def test_paper_tokenizer_and_world_model_are_the_papers():
    tok = tokenizer_config(compose_cfg(["experiment=paper_tokenizer"]))
    assert tuple(tok.latent_shape) == (50, 50)
    # 512 codes in all: the AM-VAE splits them over its air / non-air codebooks (256 each).
    assert tok.latent_channels == 128 and sum(tok.codebook_sizes) == 512
    wm = world_model_config(
        compose_cfg(["experiment=paper_world_model", "stage.tokenizer_ckpt=t.pt"]), tok
    )
    assert tuple(wm.token_grid) == (50, 50) and wm.history_frames == 5 and wm.future_frames == 6
