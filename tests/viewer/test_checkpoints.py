"""Models for the viewer from checkpoint files; missing files give one reason each."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.planning import PlanRequest, save_planner_bundle
from renderworld.training.checkpoint import CheckpointError
from renderworld.viewer.checkpoints import load_viewer_models
from tests.viewer.helpers import (
    img2occ_checkpoint,
    tokenizer_checkpoint,
    world_model_checkpoint,
)


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


def test_a_world_model_checkpoint_plans_like_the_model_it_holds(tiny_models, tmp_path):
    import numpy as np

    from renderworld.planning import PlanRequest

    _, tok, planner = tiny_models
    tok_path = tokenizer_checkpoint(tok, tmp_path / "tok.pt")
    wm_path = world_model_checkpoint(planner.world_model, tok_path, tmp_path / "wm.pt")
    loaded = load_viewer_models(tokenizer_ckpt=tok_path, world_model_ckpt=wm_path)["planner"]
    rng = np.random.default_rng(0)
    occ = rng.choice(np.array([4, 11, 17], np.uint8), size=(5, 50, 50, 4), p=[0.05, 0.15, 0.8])
    req = PlanRequest(occ, np.tile(np.float32([[2.0, 0.0]]), (4, 1)), "straight")
    a, b = planner.plan(req), loaded.plan(req)
    np.testing.assert_array_equal(a.trajectory, b.trajectory)
    np.testing.assert_array_equal(a.occupancy_forecast, b.occupancy_forecast)
    other = tmp_path / "other_tok.pt"
    other.write_bytes(tok_path.read_bytes())
    with pytest.warns(UserWarning, match="differs from the tokenizer the world model was trained"):
        load_viewer_models(tokenizer_ckpt=other, world_model_ckpt=wm_path)


def test_a_pose_warp_world_model_draws_its_forecast_in_its_own_frames(
    tiny_models, converted, tmp_path
):
    # The main job's pose-aware forecaster: loaded through the same checkpoint path; its plans
    # carry the predicted headings the forecast frames are drawn in.
    from renderworld.data import load_infos
    from renderworld.viewer.model_layers import ForecastLayer
    from renderworld.world.pose import PoseWarpWorldModel

    _, tok, planner = tiny_models
    tok_path = tokenizer_checkpoint(tok, tmp_path / "tok.pt")
    torch.manual_seed(1)
    pw = PoseWarpWorldModel(planner.world_model.config, anchors="ctr_cv")
    with torch.no_grad():  # a pose head that turns: headings differ from the travel direction
        for p in pw.pose.parameters():
            p.add_(0.05 * torch.randn_like(p))
    # A run on a 0.8 m grid (the tokenizer's 50 x 50 x 4 over +-20 m): the warp must use it.
    grid = {"name": "fine20", "range_min": [-20.0, -20.0, -1.0], "range_max": [20.0, 20.0, 5.4],
            "shape": [50, 50, 4]}  # fmt: skip
    path = world_model_checkpoint(
        pw, tok_path, tmp_path / "wm.pt", "pose_warp", grid=grid, pose_anchors="ctr_cv"
    )
    models = load_viewer_models(tokenizer_ckpt=tok_path, world_model_ckpt=path)
    loaded = models["planner"]
    assert loaded is not None and loaded.kind == "pose_warp" and "forecast" not in models.reasons
    assert tuple(loaded.grid.range_min) == (-20.0, -20.0, -1.0)
    assert tuple(loaded.grid.range_max) == (20.0, 20.0, 5.4)
    for k, v in pw.state_dict().items():
        assert torch.equal(loaded.world_model.state_dict()[k], v), k
    root, infos_dir = converted
    layer = ForecastLayer(loaded, load_infos(infos_dir, "val"), root)
    item = layer.data[0]
    result = loaded.plan(
        PlanRequest(item["occ"].numpy(), item["ego_displacements"].numpy(), "straight",
                    ego_yaws=item["history_poses"][:, 2].numpy())
    )  # fmt: skip
    assert result.yaws is not None and result.yaws.shape == (loaded.config.future_frames,)
    assert np.isfinite(result.yaws).all() and np.abs(result.yaws).max() > 0


def test_an_img2occ_checkpoint_keeps_weights_and_readout_threshold(tiny_models, tmp_path):
    img2occ = tiny_models[0]
    path = img2occ_checkpoint(img2occ, tmp_path / "i2o.pt")
    loaded = load_viewer_models(img2occ_ckpt=path)["img2occ"]
    assert not loaded.training
    for k, v in img2occ.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k


def test_a_file_of_another_stage_is_an_error_naming_it(tiny_models, tmp_path):
    _, tok, _ = tiny_models
    path = tokenizer_checkpoint(tok, tmp_path / "tok.pt")
    with pytest.raises(CheckpointError, match=r"tok\.pt.*expected stage 'img2occ'"):
        load_viewer_models(img2occ_ckpt=path)
