"""Models for the viewer from checkpoint files; missing files give one reason each."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import yaml

from renderworld.planning import save_planner_bundle
from renderworld.training.checkpoint import CheckpointError, save_checkpoint
from renderworld.viewer.checkpoints import load_viewer_models


def _tokenizer_ckpt(tok, path):
    """A ``tokenizer`` checkpoint of ``tok`` with the run config its loader reads."""
    cfg = dataclasses.asdict(tok.cfg)
    model = {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()}
    model.pop("grid_shape")
    config = {
        "grid": {"name": "coarse", "range_min": [-40.0, -40.0, -1.0],
                 "range_max": [40.0, 40.0, 5.4], "shape": list(tok.cfg.grid_shape)},
        "stage": {"name": "tokenizer", "model": model},
    }  # fmt: skip
    state = {"schema_version": 1, "stage": "tokenizer", "step": 0,
             "config": yaml.safe_dump(config), "model": tok.state_dict()}  # fmt: skip
    return save_checkpoint(state, path)


def test_loads_given_files_and_explains_missing_ones(tiny_models, tmp_path):
    _, tok, planner = tiny_models
    tok_path = _tokenizer_ckpt(tok, tmp_path / "tok.pt")
    bundle = save_planner_bundle(tmp_path / "planner.pt", tok, planner.world_model)
    models = load_viewer_models(
        img2occ_ckpt=tmp_path / "absent.pt", tokenizer_ckpt=tok_path, planner_bundle=bundle
    )
    assert models["img2occ"] is None
    assert models.reasons == {"img2occ": f"img2occ_ckpt {str(tmp_path / 'absent.pt')!r} "
                                         "does not exist"}  # fmt: skip
    for k, v in tok.state_dict().items():
        assert torch.equal(models["tokenizer"].state_dict()[k], v), k
    assert models["planner"].config == planner.config
    # A world model without its tokenizer cannot plan: said once, for the forecast layer.
    models = load_viewer_models(world_model_ckpt=bundle)
    assert models["planner"] is None and "tokenizer_ckpt" in models.reasons["forecast"]


def test_a_file_of_another_stage_is_an_error_naming_it(tiny_models, tmp_path):
    _, tok, _ = tiny_models
    path = _tokenizer_ckpt(tok, tmp_path / "tok.pt")
    with pytest.raises(CheckpointError, match=r"tok\.pt.*expected stage 'img2occ'"):
        load_viewer_models(img2occ_ckpt=path)
