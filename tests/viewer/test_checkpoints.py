"""Models for the viewer from checkpoint files; missing files give one reason each."""

from __future__ import annotations

import pytest
import torch

from renderworld.planning import save_planner_bundle
from renderworld.training.checkpoint import CheckpointError
from renderworld.viewer.checkpoints import load_viewer_models
from tests.viewer.helpers import tokenizer_checkpoint


def test_loads_given_files_and_explains_missing_ones(tiny_models, tmp_path):
    _, tok, planner = tiny_models
    tok_path = tokenizer_checkpoint(tok, tmp_path / "tok.pt")
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
    path = tokenizer_checkpoint(tok, tmp_path / "tok.pt")
    with pytest.raises(CheckpointError, match=r"tok\.pt.*expected stage 'img2occ'"):
        load_viewer_models(img2occ_ckpt=path)
