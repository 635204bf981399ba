"""The world_model stage with stage.forecaster=pose_warp: leak-free forecasts, train and eval."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from torch.utils.data import DataLoader

from renderworld.constants import FREE_ID
from renderworld.training import evaluate, train
from renderworld.training.stages.world_model import WorldModelStage
from renderworld.training.stages.world_model.report import (
    CHECKED,
    CHECKED_HISTORY_COMMAND,
    HISTORY_COMMAND,
)
from renderworld.training.stages.world_model.report import REPORT_BASENAME as REPORT
from renderworld.world.forecast import movers_of, warp_current
from renderworld.world.mover_head import MoverHead
from renderworld.world.pose import PoseWarpWorldModel

from . import test_world_model_stage as base
from .conftest import compose_cfg
from .test_world_model_tokens import busy_stage, perturb_future

HISTORY, FUTURE = base.HISTORY, base.FUTURE
# The stage tests' module fixtures: the tiny fixture, its tiny tokenizer and the overrides.
converted, tokenizer_ckpt, wm_overrides = base.converted, base.tokenizer_ckpt, base.wm_overrides

POSE = ["stage.forecaster=pose_warp"]


def base_tok(overrides: list[str]) -> str:
    """The tokenizer checkpoint of the overrides."""
    return next(o.split("=", 1)[1] for o in overrides if o.startswith("stage.tokenizer_ckpt="))


def _stage(wm_overrides, tmp_path):
    stage, model, val_set = busy_stage([*wm_overrides, *POSE], tmp_path)
    assert isinstance(model, PoseWarpWorldModel)
    return stage, model, val_set


@pytest.mark.parametrize("movers", ["static", "object_cv", "learned"])
def test_changing_the_future_ground_truth_leaves_the_forecast_unchanged(
    wm_overrides, tmp_path, movers
):
    stage, model, val_set = _stage(wm_overrides, tmp_path)
    model.movers = movers
    if movers == "learned":  # a head that is not the constant-velocity rule
        torch.manual_seed(0)
        model.mover_head = MoverHead(model.config.history_frames, model.config.future_frames)
        torch.nn.init.normal_(model.mover_head.mlp[-1].weight, std=0.5)
    batch = next(iter(DataLoader(val_set, batch_size=2)))
    setting = stage.eval_settings[0]
    h = HISTORY
    if movers != "static":  # the mover path does move objects in this batch
        args = (batch["occ"][:, :h], batch["history_poses"], batch["future_poses"], stage.grid)
        assert not torch.equal(warp_current(*args, movers_of(model)), warp_current(*args, "static"))
    yaw, yaw2 = {}, {}
    fc, traj = stage.forecast(model, batch, setting, None, yaw)
    fc2, traj2 = stage.forecast(model, perturb_future(batch, HISTORY), setting, None, yaw2)
    planned = {"model", HISTORY_COMMAND, CHECKED, CHECKED_HISTORY_COMMAND, "cv_traj", "ctr_traj"}
    assert set(yaw) == set(yaw2) == planned
    for k in yaw:  # the planned headings scored beside L2
        assert torch.equal(yaw[k], yaw2[k]), k
    for k in ("model", "model_warp", "model_net", HISTORY_COMMAND, "copy_paste", "warp_cv",
              "warp_ctr", "warp_object_cv"):  # fmt: skip
        assert torch.equal(fc[k], fc2[k]), k
    for k in planned:  # the checked plans too: they read the model's own forecast only
        assert torch.equal(traj[k], traj2[k]), k
    # The history does drive it (the test above could not pass by ignoring every input).
    moved = copy.deepcopy(batch)
    moved["history_poses"][:, :-1, 2] += 0.3
    fc3, traj3 = stage.forecast(model, moved, setting, None)
    assert not torch.equal(traj3["model"], traj["model"])
    assert not torch.equal(fc3["model_warp"], fc["model_warp"])


def test_forecast_takes_the_warp_on_the_grid_and_the_tokens_elsewhere(wm_overrides, tmp_path):
    stage, model, val_set = _stage(wm_overrides, tmp_path)
    batch = next(iter(DataLoader(val_set, batch_size=2)))
    fc, _ = stage.forecast(model, batch, stage.eval_settings[0], None)
    same_as_warp = fc["model"] == fc["model_warp"]
    same_as_net = fc["model"] == fc["model_net"]
    assert (same_as_warp | same_as_net | (fc["model"] == FREE_ID)).all()
    # Classes the current frame does not hold come from neither the warp nor the fill.
    h = HISTORY
    for b in range(2):
        now = set(batch["occ"][b, h - 1].unique().tolist())
        assert set(fc["model"][b].unique().tolist()) <= now | {FREE_ID}
    assert fc["model"].shape == (2, FUTURE, *stage.grid.shape)


def test_the_pose_warm_up_fits_the_pose_head_alone(wm_overrides, tmp_path):
    from renderworld.training.stages.world_model.pose_warmup import warm_up_pose_head
    from renderworld.training.stages.world_model.pose_warp import pose_terms

    cfg = compose_cfg([*wm_overrides, *POSE, "stage.pose_mirror=true", f"run_dir={tmp_path}"])
    stage = WorldModelStage(cfg)
    train_set, _ = stage.build_datasets(cfg)
    model = stage.build_model(cfg).train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    batch = next(iter(DataLoader(train_set, batch_size=len(train_set))))
    loss0 = float(pose_terms(stage, model, batch)["pose"])
    logs = warm_up_pose_head(stage, model, train_set, 60, lr=4e-3, weight_decay=0.01,
                             batch_size=2, seed=0, progress=False)  # fmt: skip
    assert float(pose_terms(stage, model, batch)["pose"]) < 0.7 * loss0
    assert logs["pose_warmup/last_loss"] < logs["pose_warmup/first_loss"]
    after = model.state_dict()
    for k, v in before.items():
        assert torch.equal(v, after[k]) != k.startswith("pose."), k  # only the pose head moved
    assert all(p.grad is None for p in model.parameters())
    with pytest.raises(ValueError, match="steps: expected an int >= 1"):
        warm_up_pose_head(stage, model, train_set, 0, lr=1e-3, weight_decay=0.0, batch_size=2,
                          seed=0)  # fmt: skip
    # The stage runs it for stage.pose_warmup_steps when the loop calls warm_start.
    cfg = compose_cfg([*wm_overrides, *POSE, "stage.pose_warmup_steps=5", f"run_dir={tmp_path}"])
    stage = WorldModelStage(cfg)
    model = stage.build_model(cfg).train()
    with pytest.raises(RuntimeError, match="pose_warmup_steps=5, stage.mover_fit_steps=0: no"):
        stage.warm_start(model)  # no training windows yet: refused, not skipped
    stage.build_datasets(cfg)
    head = {k: v.clone() for k, v in model.pose.state_dict().items()}
    stage.warm_start(model)
    assert any(not torch.equal(v, model.pose.state_dict()[k]) for k, v in head.items())


def _trend_reading_head(wm_overrides, tmp_path):
    """(overrides, stage, a training batch of 2, a model in training mode whose pose head reads
    the history's trend)."""
    over = [*wm_overrides, *POSE, f"run_dir={tmp_path}"]
    stage = WorldModelStage(compose_cfg(over))
    train_set, _ = stage.build_datasets(compose_cfg(over))
    batch = next(iter(DataLoader(train_set, batch_size=2)))
    torch.manual_seed(0)
    model = stage.build_model(compose_cfg(over)).train()
    with torch.no_grad():
        model.pose.mlp[-1].weight.normal_(0.0, 0.1)
    return over, stage, batch, model


def test_past_motion_dropout_shows_the_pose_head_steady_histories_in_training_only(
    wm_overrides, tmp_path
):
    from renderworld.training.stages.world_model.pose_warp import pose_terms
    from renderworld.world.pose_inputs import steady_history

    over, stage, batch, model = _trend_reading_head(wm_overrides, tmp_path)
    steady = dict(batch, history_poses=steady_history(batch["history_poses"].double()))
    assert not torch.allclose(steady["history_poses"].float(), batch["history_poses"].float())
    plain, on_steady = pose_terms(stage, model, batch), pose_terms(stage, model, steady)
    drop = WorldModelStage(compose_cfg([*over, "stage.pose_history_dropout=1.0"]))
    drop.build_datasets(compose_cfg([*over, "stage.pose_history_dropout=1.0"]))
    torch.testing.assert_close(pose_terms(drop, model, batch)["pose"], on_steady["pose"])
    assert not torch.allclose(plain["pose"], on_steady["pose"])
    model.eval()  # evaluation and planning read the history as it is
    torch.testing.assert_close(
        pose_terms(drop, model, batch)["pose"], pose_terms(stage, model, batch)["pose"]
    )
    with pytest.raises(ValueError, match="stage.pose_history_dropout: expected a fraction"):
        WorldModelStage(compose_cfg([*over, "stage.pose_history_dropout=1.5"]))


def test_history_noise_moves_the_pose_heads_history_in_training_only(wm_overrides, tmp_path):
    from renderworld.training.stages.world_model.pose_warp import pose_terms

    over, stage, batch, model = _trend_reading_head(wm_overrides, tmp_path)
    noisy = WorldModelStage(compose_cfg([*over, "stage.pose_history_noise_m=0.05"]))
    noisy.build_datasets(compose_cfg([*over, "stage.pose_history_noise_m=0.05"]))
    plain = pose_terms(stage, model, batch)["pose"]
    torch.manual_seed(1)
    first = pose_terms(noisy, model, batch)["pose"]
    torch.manual_seed(1)
    torch.testing.assert_close(pose_terms(noisy, model, batch)["pose"], first)  # seeded
    assert not torch.allclose(first, plain)
    model.eval()  # evaluation and planning read the history as it is
    torch.testing.assert_close(pose_terms(noisy, model, batch)["pose"],
                               pose_terms(stage, model, batch)["pose"])  # fmt: skip
    with pytest.raises(ValueError, match="stage.pose_history_noise_m: expected a number >= 0"):
        WorldModelStage(compose_cfg([*over, "stage.pose_history_noise_m=-0.1"]))


def test_each_pose_head_of_an_ensemble_trains_on_its_own_loss(wm_overrides, tmp_path):
    from renderworld.training.stages.world_model.pose_warp import pose_terms
    from renderworld.world.pose import PoseHead

    over = [*wm_overrides, *POSE, "stage.pose_mirror=true", f"run_dir={tmp_path}"]
    cfg = compose_cfg([*over, "stage.pose_heads=3"])
    stage = WorldModelStage(cfg)
    train_set, _ = stage.build_datasets(cfg)
    model = stage.build_model(cfg).train()
    assert len(model.pose.members) == 3
    batch = next(iter(DataLoader(train_set, batch_size=2)))
    terms = pose_terms(stage, model, batch)
    # Each member alone, as a one-head model would score it: the ensemble's loss is their sum.
    single = stage.build_model(compose_cfg(over)).train()
    alone = []
    for m in model.pose.members:
        assert isinstance(m, PoseHead)
        single.pose = m
        alone.append(pose_terms(stage, single, batch))
    torch.testing.assert_close(terms["pose"], sum(t["pose"] for t in alone))
    torch.testing.assert_close(terms["pose_l2"], sum(t["pose_l2"] for t in alone) / 3)
    terms["pose"].backward()
    for m, t in zip(model.pose.members, alone, strict=True):
        own = torch.autograd.grad(t["pose"], list(m.parameters()))
        for p, g in zip(m.parameters(), own, strict=True):
            torch.testing.assert_close(p.grad, g)  # each gets the gradient it would get alone


def test_a_frozen_pose_head_gets_no_gradient_in_the_joint_training(wm_overrides, tmp_path):
    for joint, frozen in ((None, False), (0, True)):
        over = [*POSE, "stage.pose_warmup_steps=2", f"run_dir={tmp_path}"]
        if joint is not None:
            over.append(f"stage.pose_joint_lr_scale={joint}")
        cfg = compose_cfg([*wm_overrides, *over])
        stage = WorldModelStage(cfg)
        train_set, _ = stage.build_datasets(cfg)
        model = stage.build_model(cfg).train()
        loss, logs = stage.loss(model, next(iter(DataLoader(train_set, batch_size=2))))
        loss.backward()
        assert float(logs["l2"]) > 0  # the pose error is still computed and logged
        assert all((p.grad is None) == frozen for p in model.pose.parameters())
        net = [p.grad for p in model.net.parameters() if p.grad is not None]
        assert net and any(bool(g.abs().sum() > 0) for g in net)  # the token network trains


def test_trains_evaluates_and_reloads_its_kind(wm_overrides, tmp_path):
    run = tmp_path / "run"
    metrics = train(compose_cfg([*wm_overrides, *POSE, f"run_dir={run}", "trainer.max_steps=3",
                                 "trainer.val_every=3", "trainer.monitor=val/model/miou_avg",
                                 "trainer.monitor_mode=max"]))  # fmt: skip
    for key in ("val/model/miou_1s", "val/model_warp/miou_1s", "val/model_net/iou_2s",
                "val/model/l2_at_horizon_2s", "val/l2"):  # fmt: skip
        assert math.isfinite(metrics[key]), key
    # Eval without stage.forecaster: the checkpoint's kind is used.
    m = evaluate(compose_cfg([*wm_overrides, f"ckpt={run / 'checkpoints' / 'last.pt'}",
                              f"run_dir={tmp_path / 'eval'}"], "eval"))  # fmt: skip
    assert m["val/model_warp/miou_1s"] == pytest.approx(metrics["val/model_warp/miou_1s"])
    rows = (tmp_path / "eval" / "world_model_eval.md").read_text()
    assert "| 3D-Occ | model, warp only |" in rows and "| 3D-Occ | model, tokens only |" in rows

    # The model given the command from the history carries every column the model carries.
    def columns(method: str) -> set[str]:
        return {k.split("/", 2)[2] for k in m if k.startswith(f"val/{method}/")}

    assert columns("model") == columns(HISTORY_COMMAND)
    assert {"heading_median_1s", "heading_mean_2s", "collision_boxes_at_horizon_1s",
            "movers_miou_1s", "l2_at_horizon_2s"} <= columns(HISTORY_COMMAND)  # fmt: skip
    import csv

    table = {r["method"]: r for r in csv.DictReader(open(tmp_path / "eval" / f"{REPORT}.csv"))}
    given = {c for c, v in table["model"].items() if v != ""}
    assert given == {c for c, v in table["model, command from history"].items() if v != ""}
    # The run bundles as a planner: the checkpoint's weights, anchors and grid.
    from renderworld.planning import load_planner
    from renderworld.training.checkpoint import load_checkpoint
    from renderworld.training.stages.world_model import export_planner_bundle

    ckpt = run / "checkpoints" / "last.pt"
    bundle = export_planner_bundle(ckpt, base_tok(wm_overrides), tmp_path / "planner.pt")
    planner = load_planner(bundle)
    # ... and the main job's planner step (tools/export_planner.py) writes the same bundle.
    import subprocess

    from .conftest import PYTHON, REPO, subprocess_env

    out = tmp_path / "job" / "planner" / "planner.pt"
    proc = subprocess.run(
        [PYTHON, "tools/export_planner.py", f"world_model_ckpt={ckpt}",
         f"tokenizer_ckpt={base_tok(wm_overrides)}", f"out={out}"],
        cwd=REPO, env=subprocess_env(), capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    via_tool = load_planner(out)
    for k, v in via_tool.world_model.state_dict().items():
        assert torch.equal(v, planner.world_model.state_dict()[k]), k
    assert planner.kind == "pose_warp" and isinstance(planner.world_model, PoseWarpWorldModel)
    stored = load_checkpoint(ckpt, expected_stage="world_model")["model"]
    for k, v in planner.world_model.state_dict().items():
        assert torch.equal(v, stored[k]), k
    stage = WorldModelStage(compose_cfg([*wm_overrides, *POSE, f"run_dir={tmp_path / 'x'}"]))
    assert planner.grid == stage.grid


def _requests(batch, n: int) -> list:
    """PlanRequests of a batch's windows: the history only (no future frame, pose or box).

    A request holds at least 5 frames and these models read 3: the two oldest rows repeat the
    first history frame standing still (the planner reads the last ``history_frames`` only).
    """
    import numpy as np

    from renderworld.constants import COMMANDS
    from renderworld.planning import PlanRequest

    h, pad = HISTORY, max(0, 5 - HISTORY)
    poses = batch["history_poses"].double().numpy()
    out = []
    for i in range(n):
        occ = batch["occ"][i, :h].numpy()
        p = np.concatenate([np.repeat(poses[i, :1], pad, axis=0), poses[i]])
        out.append(PlanRequest(np.concatenate([np.repeat(occ[:1], pad, axis=0), occ]),
                               np.diff(p[:, :2], axis=0), COMMANDS[int(batch["command"][i])],
                               ego_yaws=p[:, 2]))  # fmt: skip
    return out


@pytest.mark.parametrize("movers", ["static", "object_cv"])
def test_bundled_planner_reproduces_the_stage_forecast(wm_overrides, tmp_path, movers):
    """plan() on the bundled pose-warp model gives the stage's own evaluation outputs: the
    planner is the model, not an approximation (the trajectory bit for bit; the forecast up
    to the round-off of another batch composition)."""
    import numpy as np

    from renderworld.planning import PlannerSession, load_planner, save_planner_bundle

    stage, model, val_set = _stage(wm_overrides, tmp_path)
    model.movers = movers
    batch = next(iter(DataLoader(val_set, batch_size=2)))
    fc, traj = stage.forecast(model, batch, stage.eval_settings[0], None)
    tok = stage._tokenizer_on(torch.device("cpu"), None)
    path = save_planner_bundle(tmp_path / "planner.pt", tok, model, grid=stage.grid)
    reqs = _requests(batch, 2)
    for fast in (False, True):  # the reference codec (the stage's) and the fast one
        planner = load_planner(path, fast=fast)
        assert planner.world_model.movers == movers
        res = planner.plan_batch(reqs)
        for i, r in enumerate(res):
            np.testing.assert_array_equal(r.trajectory, traj["model"][i].numpy())
            # The stage encodes the history (cached per frame) apart from the warped frames and
            # decodes step by step; the planner encodes and decodes in one batch. Kernels whose
            # summation order follows the batch size (oneDNN on AVX-512 CPUs) can flip a code
            # at a near-tie: allow 1 % of the voxels, a sixth of what the token network changes.
            differ = (r.occupancy_forecast != fc["model"][i].numpy()).mean()
            assert differ <= 0.01, (i, differ)
            network = (fc["model"][i] != fc["model_warp"][i]).double().mean().item()
            assert network >= 0.05, network  # the tolerance is far below the network's part
        # Batch of one: the same model, GEMMs of another batch size (float32 round-off only).
        one = planner.plan(reqs[1], forecast=False)
        np.testing.assert_allclose(one.trajectory, traj["model"][1].numpy(), rtol=0, atol=1e-5)
        session = PlannerSession(planner)
        for frame in reqs[0].occupancy[-HISTORY:]:
            session.push(frame)
        again = session.plan(reqs[0].ego_displacements, reqs[0].command,
                             ego_yaws=reqs[0].ego_yaws)  # fmt: skip
        ref = planner.plan(reqs[0])
        np.testing.assert_array_equal(again.trajectory, ref.trajectory)
        np.testing.assert_array_equal(again.occupancy_forecast, ref.occupancy_forecast)
    assert not np.array_equal(fc["model"][0].numpy(), fc["model_warp"][0].numpy())


def test_extra_train_roots_add_their_train_windows(wm_overrides, converted, tmp_path):
    root, infos = converted
    extra = tmp_path / "extra"
    extra.mkdir()
    for child in root.iterdir():
        (extra / child.name).symlink_to(child)
    (extra / "renderworld_infos").mkdir()
    (extra / "renderworld_infos" / "v1.0-mini").symlink_to(infos)
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}"])
    one, val = WorldModelStage(cfg).build_datasets(cfg)
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}", f"stage.extra_train_roots=[{extra}]"])
    two, val2 = WorldModelStage(cfg).build_datasets(cfg)
    assert len(two) == 2 * len(one) and len(val2) == len(val)
    assert torch.equal(two[len(one)]["occ"], one[0]["occ"])
    bad = compose_cfg(
        [*wm_overrides, f"run_dir={tmp_path}", f"stage.extra_train_roots=[{tmp_path}]"]
    )
    with pytest.raises(ValueError, match="stage.extra_train_roots: .* does not exist"):
        WorldModelStage(bad).build_datasets(bad)
    # A root converted under its own version (a scenario library) is found by that version.
    (extra / "renderworld_infos" / "v1.0-mini").rename(extra / "renderworld_infos" / "v1.0-lib")
    three, _ = WorldModelStage(cfg).build_datasets(cfg)
    assert len(three) == len(two)
    (extra / "renderworld_infos" / "v1.0-other").symlink_to(infos)
    with pytest.raises(ValueError, match="several versions .* none is dataset.version"):
        WorldModelStage(cfg).build_datasets(cfg)


def test_pose_step_weighting_names():
    from renderworld.training.stages.world_model.pose_warp import pose_step_weights

    assert pose_step_weights("uniform", 6) is None
    w = pose_step_weights("inverse", 3)
    torch.testing.assert_close(w, torch.tensor([1.0, 0.5, 1 / 3]) / (11 / 18))
    with pytest.raises(ValueError, match="stage.pose_step_weighting: expected"):
        pose_step_weights("log", 3)


def test_both_settings_score_alike_on_pseudo_labels_equal_to_gt(wm_overrides, converted, tmp_path):
    run = tmp_path / "run"
    train(compose_cfg([*wm_overrides, *POSE, f"run_dir={run}", "trainer.max_steps=2",
                       "trainer.val_every=0"]))  # fmt: skip
    ckpt = run / "checkpoints" / "last.pt"
    same = base._pseudo_labels(converted, tmp_path / "same", free=False)
    m = evaluate(compose_cfg([*wm_overrides, f"ckpt={ckpt}", f"run_dir={tmp_path / 'a'}",
                              f"pseudo_labels={same}", f"camera_ckpt={ckpt}"], "eval"))  # fmt: skip
    scored = [k for k in m if k.startswith("val/model") and "/" in k[4:]]
    assert "val/model_warp/miou_1s" in scored and "val/camera/model_net/miou_1s" in m
    for k in scored:
        assert m[f"val/camera/{k[4:]}"] == pytest.approx(m[k], rel=1e-9, nan_ok=True), k


def test_trains_in_the_camera_setting(wm_overrides, converted, tmp_path):
    labels = base._pseudo_labels(converted, tmp_path / "pseudo", free=False)
    metrics = train(compose_cfg([*wm_overrides, *POSE, f"run_dir={tmp_path / 'run'}",
                                 f"stage.occ_root={labels}", "trainer.max_steps=2",
                                 "trainer.val_every=2"]))  # fmt: skip
    assert math.isfinite(metrics["val/model/miou_1s"]) and math.isfinite(metrics["val/l2"])


def test_a_held_out_dataset_without_a_train_split_evaluates(wm_overrides, converted, tmp_path):
    """The interaction split puts every scene in val: evaluation must not need infos_train."""
    import shutil

    _, infos = converted
    val_only = tmp_path / "infos"
    val_only.mkdir()
    for f in infos.iterdir():
        if f.is_file() and not f.name.startswith("infos_train"):
            shutil.copy(f, val_only / f.name)
    over = [o for o in wm_overrides if not o.startswith("stage.infos_dir=")]
    cfg = compose_cfg([*over, f"stage.infos_dir={val_only}", f"run_dir={tmp_path}"])
    stage = WorldModelStage(cfg)
    with pytest.raises(Exception, match="infos_train"):
        stage.build_datasets(cfg)  # training does need it ...
    val = stage.build_val_dataset(cfg)  # ... evaluation does not
    full = compose_cfg([*wm_overrides, f"run_dir={tmp_path}"])
    train_set, val_set = WorldModelStage(full).build_datasets(full)
    assert len(val) == len(val_set) > 0
    # dataset.val_split=all: every scene of the dataset (here its train and its val scene).
    every = compose_cfg([*wm_overrides, f"run_dir={tmp_path}", "dataset.val_split=all"])
    windows = WorldModelStage(every).build_val_dataset(every)
    assert len(windows) == len(train_set) + len(val_set)
    assert {windows[i]["meta"]["scene"] for i in range(len(windows))} == {
        x["meta"]["scene"] for part in (train_set, val_set) for x in part
    }


def test_a_later_validation_reuses_the_model_free_rows_and_scores_alike(wm_overrides, tmp_path):
    """The baselines and references are scored once per validation set: a second validation
    of the same model gives every figure of the first, and a changed model changes its rows
    only."""
    from renderworld.training.stages.world_model.evaluation import MODEL_FREE_METHODS

    stage, model, val_set = _stage(wm_overrides, tmp_path)
    loader = DataLoader(val_set, batch_size=2)
    first = stage.compute_metrics(stage.evaluate(model, loader))
    assert len(stage._fixed_stats) == 1

    def not_again(*args, **kwargs):
        raise AssertionError("a later validation recomputed a model-free row")

    stage.references = not_again  # the references read the future: scored once only
    again = stage.compute_metrics(stage.evaluate(model, loader))
    assert set(first) == set(again)
    for k, v in first.items():
        assert v == again[k] or (math.isnan(v) and math.isnan(again[k])), k
    with torch.no_grad():
        for p in model.pose.parameters():
            p.add_(0.05)
    moved = stage.compute_metrics(stage.evaluate(model, loader))
    assert moved["model/l2_at_horizon_avg"] != first["model/l2_at_horizon_avg"]
    for k, v in first.items():
        if k.split("/")[0] in MODEL_FREE_METHODS:
            assert v == moved[k] or (math.isnan(v) and math.isnan(moved[k])), k


def test_the_evaluations_check_knobs_reach_the_checked_plans(wm_overrides, tmp_path, monkeypatch):
    from omegaconf import open_dict

    import renderworld.planning.checked as checked

    stage, model, val_set = _stage(wm_overrides, tmp_path)
    batch = next(iter(DataLoader(val_set, batch_size=2)))
    seen, plan = [], checked.check_plan

    def spy(*args, **kwargs):
        seen.append(args[4] if len(args) > 4 else kwargs.get("config"))
        return plan(*args, **kwargs)

    monkeypatch.setattr(checked, "check_plan", spy)
    stage.forecast(model, batch, stage.eval_settings[0], None)
    assert seen and all(c is None for c in seen)  # the planner's defaults
    seen.clear()
    with open_dict(stage.cfg):
        stage.cfg.check = {"plan_margin": 0.5, "offsets_m": [0.0]}  # as check={...} sets it
    stage.forecast(model, batch, stage.eval_settings[0], None)
    assert seen and all(c.plan_margin == 0.5 and c.offsets_m == (0.0,) for c in seen)
    with open_dict(stage.cfg):
        stage.cfg.check = {"bogus": 1}
    with pytest.raises(ValueError, match="check.bogus: CheckConfig has no such knob"):
        stage.forecast(model, batch, stage.eval_settings[0], None)
