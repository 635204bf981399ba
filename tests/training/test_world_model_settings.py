"""The world model's stage settings: every option is checked when the stage is built."""

from __future__ import annotations

import pytest

from renderworld.training.stages.world_model import WorldModelStage
from renderworld.training.stages.world_model.settings import (
    FORECASTER_KINDS,
    POSE_STEP_WEIGHTINGS,
    build_world_model,
    stage_settings,
    world_model_config,
)
from renderworld.world.pose import ANCHORS

from .conftest import compose_cfg

BASE = ["stage=world_model", "stage.tokenizer_ckpt=tok.pt"]


@pytest.mark.parametrize(
    "override, option",
    [
        ("stage.pose_yaw_weight=-1", "stage.pose_yaw_weight"),
        ("stage.pose_yaw_weight=heavy", "stage.pose_yaw_weight"),
        ("stage.lambda_pose=-0.5", "stage.lambda_pose"),
        ("stage.pose_mirror=maybe", "stage.pose_mirror"),
        ("stage.pose_anchors=cv", "stage.pose_anchors"),
        ("stage.pose_step_weighting=log", "stage.pose_step_weighting"),
        ("stage.pose_kinematics=2", "stage.pose_kinematics"),
        ("stage.pose_motion_frames=-1", "stage.pose_motion_frames"),
        ("stage.pose_motion_frames=9", "stage.pose_motion_frames"),
        ("stage.pose_agents=-1", "stage.pose_agents"),
        ("stage.pose_agents=2.5", "stage.pose_agents"),
        ("stage.pose_leader=2", "stage.pose_leader"),
        ("stage.pose_leader_stop=2", "stage.pose_leader_stop"),
        ("stage.pose_heads=0", "stage.pose_heads"),
        ("stage.pose_heads=true", "stage.pose_heads"),
        ("stage.pose_bev_pool=0", "stage.pose_bev_pool"),
        ("stage.pose_bev_pool=2.5", "stage.pose_bev_pool"),
        ("stage.pose_lr_scale=0", "stage.pose_lr_scale"),
        ("stage.pose_lr_scale=-1", "stage.pose_lr_scale"),
        ("stage.pose_warmup_steps=-5", "stage.pose_warmup_steps"),
        ("stage.pose_warmup_steps=1.5", "stage.pose_warmup_steps"),
        ("stage.pose_joint_lr_scale=-1", "stage.pose_joint_lr_scale"),
        ("stage.pose_joint_lr_scale=fast", "stage.pose_joint_lr_scale"),
    ],
)
@pytest.mark.parametrize("forecaster", FORECASTER_KINDS)
def test_a_bad_pose_option_fails_when_the_stage_is_built(override, option, forecaster):
    cfg = compose_cfg([*BASE, f"stage.forecaster={forecaster}", override])
    with pytest.raises(ValueError, match=f"^{option}: expected"):
        stage_settings(cfg)
    with pytest.raises(ValueError, match=f"^{option}: expected"):
        WorldModelStage(cfg)


def test_the_pose_options_reach_the_settings():
    cfg = compose_cfg(
        [
            *BASE,
            "stage.forecaster=pose_warp",
            "stage.pose_yaw_weight=2.5",
            "stage.lambda_pose=0.25",
            "stage.pose_mirror=true",
            "stage.pose_anchors=ctr_cv",
            "stage.pose_step_weighting=inverse",
        ]
    )
    st = WorldModelStage(cfg).settings
    assert (st.pose_yaw_weight, st.lambda_pose, st.pose_mirror) == (2.5, 0.25, True)
    assert (st.pose_anchors, st.pose_step_weighting) == ("ctr_cv", "inverse")
    assert set(ANCHORS) >= {"ctr", "ctr_cv"} and POSE_STEP_WEIGHTINGS == ("uniform", "inverse")


def test_the_built_pose_model_uses_the_configured_anchors():
    from types import SimpleNamespace

    cfg = compose_cfg([*BASE, "stage.forecaster=pose_warp", "stage.pose_anchors=ctr_cv"])
    tok = SimpleNamespace(codebook_sizes=(16,), latent_shape=(4, 4))
    model = build_world_model("pose_warp", world_model_config(cfg, tok), cfg)
    assert model.pose.anchors == "ctr_cv"


def test_the_pose_head_gets_its_kinematics_and_its_own_learning_rate():
    from types import SimpleNamespace

    from renderworld.training.config import OptimizerConfig
    from renderworld.training.optim import default_param_groups

    over = ["stage.forecaster=pose_warp", "stage.pose_kinematics=true", "stage.pose_lr_scale=4"]
    cfg = compose_cfg([*BASE, *over, "stage.pose_motion_frames=2", "stage.pose_agents=3"])
    tok = SimpleNamespace(codebook_sizes=(16,), latent_shape=(4, 4))
    model = build_world_model("pose_warp", world_model_config(cfg, tok), cfg)
    assert model.pose.kinematics and model.pose.motion_frames == 2 and model.pose.agents == 3
    stage = WorldModelStage(cfg)
    assert stage.lr_scales() == {"pose.": 4.0}
    groups = default_param_groups(model, OptimizerConfig(lr=1e-3), stage.lr_scales())
    pose = {id(p) for p in model.pose.parameters()}
    for g in groups:
        mine = {id(p) in pose for p in g["params"]}
        assert len(mine) == 1  # a group holds pose-head parameters only, or none
        assert g.get("lr", 1e-3) == pytest.approx(4e-3 if mine == {True} else 1e-3)
    assert sum(len(g["params"]) for g in groups) == len(list(model.parameters()))
    # The token forecaster has no pose head: one rate.
    cfg = compose_cfg([*BASE, "stage.forecaster=tokens", "stage.pose_lr_scale=4"])
    assert WorldModelStage(cfg).lr_scales() == {}


def test_the_joint_rate_of_the_pose_head_is_its_own_or_frozen(monkeypatch):
    from renderworld.training.stages.world_model import stage as stage_module

    over = ["stage.forecaster=pose_warp", "stage.pose_lr_scale=4", "stage.pose_warmup_steps=10"]
    assert WorldModelStage(compose_cfg([*BASE, *over])).lr_scales() == {"pose.": 4.0}
    cfg = compose_cfg([*BASE, *over, "stage.pose_joint_lr_scale=0.5"])
    stage = WorldModelStage(cfg)
    assert stage.lr_scales() == {"pose.": 0.5}
    # The warm-up keeps stage.pose_lr_scale: 4 x optimizer.lr, not the joint 0.5 x.
    seen = {}
    monkeypatch.setattr(stage_module, "warm_up_pose_head",
                        lambda *a, **kw: seen.update(steps=a[3], lr=kw["lr"]) or {})  # fmt: skip
    stage._train_set = [None] * 8
    stage.warm_start(model=None)
    assert seen == {"steps": 10, "lr": pytest.approx(4 * float(cfg.optimizer.lr))}
    cfg = compose_cfg([*BASE, *over, "stage.pose_joint_lr_scale=0"])
    stage = WorldModelStage(cfg)
    assert stage.settings.pose_joint_lr_scale == 0.0 and stage.lr_scales() == {}
    # Frozen without a warm-up the head would never be fitted: refused, naming both keys.
    bad = [*BASE, "stage.forecaster=pose_warp", "stage.pose_joint_lr_scale=0"]
    with pytest.raises(ValueError, match="pose_joint_lr_scale=0 .*pose_warmup_steps > 0"):
        WorldModelStage(compose_cfg(bad))
