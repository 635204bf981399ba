"""The ``world_model`` stage on the converted tiny fixture with a tiny tokenizer checkpoint.

The tiny fixture has 8 keyframes per scene (one train scene, one val scene), so the stage runs
with history 3 and future 4 (2 windows per split; horizons 1 s and 2 s).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import subprocess

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Subset

from data_converters import ConvertOptions, create_data
from renderworld.constants import GRIDS
from renderworld.data import OccSequenceDataset, load_infos
from renderworld.metrics import ForecastMetric, OccupancyMetric, PlanningMetric, heading_error_deg
from renderworld.planning import PlanRequest, load_planner
from renderworld.training import CheckpointError, evaluate, train
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.stages.world_model import (
    WorldModelStage,
    export_planner_bundle,
    world_model_config,
)
from renderworld.world import (
    WorldModel,
    constant_turn_rate_poses,
    constant_velocity_trajectory,
    copy_paste_forecast,
    gt_movers_reference,
    object_constant_velocity_forecast,
    warp_along_poses,
)
from renderworld.world.movers import gt_pose_movers_reference

from .conftest import PYTHON, REPO, compose_cfg, subprocess_env

HISTORY, FUTURE = 3, 4
TINY_MODEL = [
    "stage.model.embed_dim=16",
    "stage.model.num_heads=2",
    "stage.model.num_scales=2",
    "stage.model.layers_per_scale=[1,1]",
]
QUIET = ["trainer.progress_bar=false", "trainer.tensorboard=false"]
TINY_TOKENIZER = [
    "stage.model.latent_channels=8",
    "stage.model.codebook_size=32",
    "stage.model.base_channels=8",
    "stage.model.num_res_blocks=1",
    "stage.model.attention=false",
]


@pytest.fixture(scope="module")
def converted(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("wm_infos")
    create_data(tiny_dataset, "v1.0-mini", out=out, options=ConvertOptions(progress=False))
    return tiny_dataset, out


def _data(converted) -> list[str]:
    root, infos = converted
    return ["grid=coarse", "trainer=cpu", f"dataset.data_root={root}", f"stage.infos_dir={infos}"]


def _tiny_tokenizer(converted, run, *extra: str):
    """Train a tiny AM-VAE for 2 steps into ``run``; its ``last.pt``."""
    cfg = compose_cfg([
        "stage=tokenizer", *_data(converted), f"run_dir={run}", *QUIET, *extra,
        "trainer.max_steps=2", "trainer.batch_size=2", "trainer.val_every=0",
        "trainer.monitor=val/miou", "trainer.monitor_mode=max", *TINY_TOKENIZER,
    ])  # fmt: skip
    train(cfg)
    return run / "checkpoints" / "last.pt"


@pytest.fixture(scope="module")
def tokenizer_ckpt(converted, tmp_path_factory):
    """A tiny AM-VAE trained for 2 steps through the tokenizer stage's own checkpoint format."""
    return _tiny_tokenizer(converted, tmp_path_factory.mktemp("tok") / "run")


@pytest.fixture(scope="module")
def wm_overrides(converted, tokenizer_ckpt):
    return [
        "stage=world_model", *_data(converted), f"stage.tokenizer_ckpt={tokenizer_ckpt}",
        f"stage.history={HISTORY}", f"stage.future={FUTURE}", *TINY_MODEL, *QUIET,
        "trainer.batch_size=2",
    ]  # fmt: skip


@pytest.fixture(scope="module")
def trained(wm_overrides, tmp_path_factory):
    """A world model trained for 4 steps (validated at the end); returns (run_dir, metrics)."""
    run = tmp_path_factory.mktemp("wm") / "run"
    cfg = compose_cfg([*wm_overrides, f"run_dir={run}", "trainer.max_steps=4",
                       "trainer.val_every=4", "trainer.monitor=val/model/miou_avg",
                       "trainer.monitor_mode=max"])  # fmt: skip
    return run, train(cfg)


def _stage_and_model(wm_overrides, tmp_path):
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}"])
    stage = WorldModelStage(cfg)
    train_set, val_set = stage.build_datasets(cfg)
    model = stage.build_model(cfg).eval()
    return stage, model, train_set, val_set


def test_trains_and_checkpoints_only_the_world_model(trained, tokenizer_ckpt):
    run, metrics = trained
    ckpt = load_checkpoint(run / "checkpoints" / "last.pt", expected_stage="world_model")
    assert ckpt["step"] == 4
    tok_keys = load_checkpoint(tokenizer_ckpt)["model"].keys()
    assert not set(ckpt["model"]) & set(tok_keys), "the frozen tokenizer must not be saved"
    model = WorldModel(world_model_config(_cfg_of(ckpt), _tok_cfg(tokenizer_ckpt)))
    model.load_state_dict(ckpt["model"], strict=True)
    assert (run / "checkpoints" / "best.pt").exists(), "monitor val/model/miou_avg exists"
    # Finite metrics for the model and every baseline, at the horizons that exist (1 s, 2 s).
    for key in [
        "val/loss", "val/token_ce", "val/l2",
        "val/model/miou_1s", "val/model/iou_2s", "val/model/miou_avg", "val/model/cam/miou_1s",
        "val/model/l2_at_horizon_1s", "val/model/l2_mean_to_horizon_2s",
        "val/model/collision_boxes_at_horizon_1s", "val/model/collision_occupancy_at_horizon_avg",
        "val/copy_paste/miou_1s", "val/copy_paste/iou_avg", "val/warp_cv/miou_2s",
        "val/warp_cv/cam/iou_1s", "val/cv_traj/l2_at_horizon_avg",
        "val/cv_traj/collision_boxes_at_horizon_2s",
    ]:  # fmt: skip
        assert math.isfinite(metrics[key]), key
    assert "val/model/miou_3s" not in metrics, "future=4 has no 3 s horizon"
    assert metrics["val/num_windows"] == 2
    # train() writes the report of its final validation too.
    assert (run / "world_model_eval.csv").exists() and (run / "world_model_eval.md").exists()


def _cfg_of(ckpt):
    from omegaconf import OmegaConf

    return OmegaConf.create(ckpt["config"])


def _tok_cfg(path):
    from renderworld.training.stages.tokenizer import load_tokenizer

    return load_tokenizer(path).cfg


def test_loss_decreases_when_overfitting_one_window(wm_overrides, tmp_path):
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}", "trainer.max_steps=40",
                       "trainer.batch_size=1", "trainer.overfit_samples=1",
                       "trainer.log_every=1", "trainer.val_every=0", "optimizer.lr=1e-2",
                       "scheduler=constant"])  # fmt: skip
    train(cfg)
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    series = {
        k: [float(r["value"]) for r in rows if r["key"] == f"train/{k}"]
        for k in ("loss", "token_ce", "l2")
    }
    assert len(series["loss"]) == 40
    assert np.mean(series["loss"][-5:]) < 0.7 * series["loss"][0], series["loss"]
    assert np.mean(series["token_ce"][-5:]) < series["token_ce"][0]
    assert np.mean(series["l2"][-5:]) < series["l2"][0]


def test_tokens_are_cached_and_equal_a_fresh_encoding(wm_overrides, tmp_path):
    stage, _, train_set, _ = _stage_and_model(wm_overrides, tmp_path)
    batch = next(iter(DataLoader(train_set, batch_size=2)))
    calls = []
    encode = stage.tokenizer.encode
    stage.tokenizer.encode = lambda x: (calls.append(len(x)), encode(x))[1]
    codes = stage.window_tokens(batch, HISTORY + FUTURE, torch.device("cpu"))
    # Two overlapping windows of 7 frames share 6: 8 distinct frames, encoded once each.
    assert calls and sum(calls) == 8
    again = stage.window_tokens(batch, HISTORY, torch.device("cpu"))
    assert sum(calls) == 8, "cached frames are not re-encoded"
    direct = encode(batch["occ"].flatten(0, 1)).indices.view(codes.shape)
    assert codes.dtype == torch.int64 and torch.equal(codes, direct)
    assert torch.equal(again, direct[:, :HISTORY])


def _other_root(converted, out):
    """A data root whose scenes and sample tokens are the fixture's but whose occupancy differs
    (every GT frame mirrored along x), converted with the fixture's infos."""
    from renderworld.data import load_occ3d_labels, save_occ3d_labels

    root, infos = converted
    for split in ("train", "val"):
        for occ_path in load_infos(infos, split)["occ_path"]:
            gt = load_occ3d_labels(root / occ_path)
            save_occ3d_labels(out / occ_path, gt.semantics[::-1].copy(), gt.mask_lidar,
                              gt.mask_camera)  # fmt: skip
    (out / "renderworld_infos").mkdir()
    (out / "renderworld_infos" / "v1.0-mini").symlink_to(infos)
    return out


def test_codes_are_keyed_by_the_data_root_of_each_frame(wm_overrides, converted, tmp_path):
    """Two roots with the same sample tokens and different occupancy never share codes: in one
    batch of the training set (the key follows the item through stage.extra_train_roots), and
    one root after the other (the token cache and the pose-warp history codes)."""
    from torch.utils.data import default_collate

    from renderworld.training.stages.world_model import pose_warp as wmp

    other = _other_root(converted, tmp_path / "other")
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}", f"stage.extra_train_roots=[{other}]"])
    stage = WorldModelStage(cfg)
    train_set, _ = stage.build_datasets(cfg)
    n, t, cpu = len(train_set) // 2, HISTORY + FUTURE, torch.device("cpu")
    a, b = default_collate([train_set[0]]), default_collate([train_set[n]])
    assert a["meta"]["sample_tokens"] == b["meta"]["sample_tokens"]
    assert not torch.equal(a["occ"], b["occ"])
    both = default_collate([train_set[0], train_set[n]])
    codes = stage.window_tokens(both, t, cpu)
    direct = stage.tokenizer.encode(both["occ"].flatten(0, 1)).indices.view(codes.shape)
    assert torch.equal(codes, direct) and not torch.equal(codes[0], codes[1])
    stage._codes.clear()
    assert torch.equal(stage.window_tokens(a, t, cpu), direct[:1])
    assert torch.equal(stage.window_tokens(b, t, cpu), direct[1:])
    # The pose-warp stage's aligned-history codes (keyed by frame and current frame).
    from renderworld.world.pose import align_history

    pose = WorldModelStage(compose_cfg([*wm_overrides, "stage.forecaster=pose_warp",
                                        f"run_dir={tmp_path}"]))  # fmt: skip
    hist = [wmp._aligned_history_codes(pose, x, "occ", "gt", None, cpu) for x in (a, b)]
    h = HISTORY - 1
    aligned = align_history(b["occ"][:, :h], b["history_poses"][:, :h], pose.grid)
    fresh = wmp.encode_frames(pose, aligned.flatten(0, 1), None, cpu)  # no keys: not cached
    assert torch.equal(hist[1].flatten(0, 1), fresh) and not torch.equal(hist[0], hist[1])


def test_baselines_match_renderworld_metrics_computed_directly(wm_overrides, tmp_path):
    stage, model, _, val_set = _stage_and_model(wm_overrides, tmp_path)
    with torch.no_grad():
        metrics = stage.compute_metrics(stage.evaluate(model, DataLoader(val_set, batch_size=2)))
    step1, fc_cam = OccupancyMetric(), ForecastMetric(FUTURE, (1.0, 2.0), mask_name="camera")
    plan = PlanningMetric(FUTURE, (1.0, 2.0))
    ctr_plan = PlanningMetric(FUTURE, (1.0, 2.0))
    gt_warp, ctr_warp = ForecastMetric(FUTURE, (1.0, 2.0)), ForecastMetric(FUTURE, (1.0, 2.0))
    obj_cv, gt_movers = ForecastMetric(FUTURE, (1.0, 2.0)), ForecastMetric(FUTURE, (1.0, 2.0))
    gt_obj_cv = ForecastMetric(FUTURE, (1.0, 2.0))
    ctr_heading = []  # heading errors at 1 s (degrees)
    turning = 0
    for i in range(len(val_set)):
        item = val_set[i]
        occ, cur = item["occ"], item["occ"][HISTORY - 1]
        step1.update(cur, occ[HISTORY])  # Copy&Paste at step 1: the current frame repeated
        gt_warp.update(warp_along_poses(cur, item["future_poses"], GRIDS["coarse"]), occ[HISTORY:])
        ctr = constant_turn_rate_poses(item["history_poses"].double(), FUTURE)
        ctr_warp.update(warp_along_poses(cur, ctr, GRIDS["coarse"]), occ[HISTORY:])
        ctr_plan.update(ctr[:, :2].float(), item["future_traj"])
        ctr_heading.append(float(heading_error_deg(ctr[1, 2], item["future_poses"][1, 2])))
        grid = GRIDS["coarse"]
        hist_poses = item["history_poses"].double()
        obj_cv.update(object_constant_velocity_forecast(occ[:HISTORY], hist_poses, FUTURE, grid),
                      occ[HISTORY:])  # fmt: skip
        gt_movers.update(gt_movers_reference(cur, occ[HISTORY:], item["future_poses"], grid),
                         occ[HISTORY:])  # fmt: skip
        gt_obj_cv.update(gt_pose_movers_reference(occ[:HISTORY], hist_poses, item["future_poses"],
                                                  grid), occ[HISTORY:])  # fmt: skip
        turning += int(item["future_poses"][:, 2].abs().max() > np.radians(5.0))
        fc_cam.update(copy_paste_forecast(cur, FUTURE), occ[HISTORY:],
                      mask=item["mask_camera"][HISTORY:])  # fmt: skip
        cv = constant_velocity_trajectory(item["ego_displacements"][: HISTORY - 1], FUTURE)
        plan.update(cv, item["future_traj"])
    assert metrics["copy_paste/miou_step1"] == pytest.approx(step1.compute()["miou"], abs=1e-12)
    assert metrics["copy_paste/iou_step1"] == pytest.approx(
        step1.compute()["iou_geometry"], abs=1e-12
    )
    direct = fc_cam.compute()
    assert metrics["copy_paste/cam/miou_2s"] == pytest.approx(direct["miou@2s"], abs=1e-12)
    assert metrics["copy_paste/cam/iou_avg"] == pytest.approx(direct["iou_avg"], abs=1e-12)
    l2 = plan.compute()
    assert metrics["cv_traj/l2_at_horizon_1s"] == pytest.approx(l2["l2_at_horizon@1s"], rel=1e-6)
    assert metrics["cv_traj/l2_mean_to_horizon_avg"] == pytest.approx(
        l2["l2_mean_to_horizon_avg"], rel=1e-6
    )
    assert metrics["warp_gt_pose/miou_2s"] == pytest.approx(gt_warp.compute()["miou@2s"])
    assert metrics["warp_ctr/iou_1s"] == pytest.approx(ctr_warp.compute()["iou@1s"])
    assert metrics["ctr_traj/l2_at_horizon_2s"] == pytest.approx(
        ctr_plan.compute()["l2_at_horizon@2s"], rel=1e-6
    )
    for name in ("miou@2s", "movers_miou@1s", "movers_miou@2s"):
        key = name.replace("@", "_")
        assert metrics[f"warp_object_cv/{key}"] == pytest.approx(obj_cv.compute()[name]), name
        assert metrics[f"warp_gt_movers/{key}"] == pytest.approx(gt_movers.compute()[name]), name
        assert metrics[f"warp_gt_object_cv/{key}"] == pytest.approx(gt_obj_cv.compute()[name])
    assert metrics["ctr_traj/heading_mean_1s"] == pytest.approx(np.mean(ctr_heading))
    assert metrics["ctr_traj/heading_median_1s"] == pytest.approx(np.median(ctr_heading), abs=0.01)
    assert "model/heading_mean_1s" not in metrics  # this model plans no heading
    assert metrics["model/turning/num_windows"] == turning
    assert metrics["model/straight/num_windows"] == len(val_set) - turning
    # The copy-paste forecast is not the GT: these numbers are not trivially 1.
    assert 0.0 < metrics["copy_paste/miou_step1"] < 1.0


def test_model_free_rows_are_scored_again_for_a_new_set_under_a_reused_id(wm_overrides, tmp_path):
    stage, model, _, val_set = _stage_and_model(wm_overrides, tmp_path)
    one, two = Subset(val_set, [0]), Subset(val_set, [1])
    with torch.no_grad():
        alone = stage.evaluate(model, DataLoader(two))
        stage._fixed_stats.clear()
        stage.evaluate(model, DataLoader(one))
        # What Python's id reuse looks like: a gone set's figures under the new set's id.
        stage._fixed_stats[id(two)] = stage._fixed_stats.pop(id(one))
        again = stage.evaluate(model, DataLoader(two))
    key = "copy_paste/full/confusion"
    assert key in again and torch.equal(again[key].cpu(), alone[key].cpu())


def test_statistics_are_additive_over_shards(wm_overrides, tmp_path):
    stage, model, _, val_set = _stage_and_model(wm_overrides, tmp_path)
    with torch.no_grad():
        # One window per batch in both (float32 model outputs depend on batch composition).
        whole = stage.evaluate(model, DataLoader(val_set, batch_size=1))
        parts = [stage.evaluate(model, DataLoader(Subset(val_set, [i]))) for i in (0, 1)]
        empty = stage.evaluate(model, DataLoader(Subset(val_set, [])))
    assert set(whole) == set(parts[0]) == set(empty)
    summed = {k: parts[0][k].cpu() + parts[1][k].cpu() + empty[k].cpu() for k in whole}
    for k in whole:
        assert torch.allclose(summed[k], whole[k].cpu().double(), rtol=1e-12), k
    a, b = stage.compute_metrics(whole), stage.compute_metrics(summed)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-12, nan_ok=True), k


def test_eval_tool_prints_the_table_and_writes_csv_and_markdown(trained, wm_overrides, tmp_path):
    run, _ = trained
    ckpt = run / "checkpoints" / "last.pt"
    proc = subprocess.run(
        [PYTHON, str(REPO / "tools" / "eval.py"), *wm_overrides, f"ckpt={ckpt}",
         f"run_dir={tmp_path}"],
        cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = proc.stdout
    assert "mIoU over classes 0..16, full volume (OccWorld protocol)" in out
    assert "L2 at horizon (UniAD); mean-to-horizon in CSV" in out
    header = next(line for line in out.splitlines() if line.startswith("setting"))
    for col in ("method", "mIoU 1s", "mIoU 2s", "mIoU avg", "IoU avg", "L2 1s", "L2 avg", "Col 2s"):
        assert col in header
    body = out.splitlines()[out.splitlines().index(header) + 1 :][:11]
    assert [line.split()[:2] for line in body] == [
        ["3D-Occ", m]
        for m in ("model", "model,", "Copy&Paste", "CV-warp", "CTR-warp", "object-CV",
                  "CV-trajectory", "CTR-trajectory", "GT-pose", "GT-pose", "GT-pose")
    ]  # fmt: skip
    rows = {r["method"]: r for r in csv.DictReader((tmp_path / "world_model_eval.csv").open())}
    assert list(rows) == [
        "model", "model, command from history", "Copy&Paste", "CV-warp", "CTR-warp",
        "object-CV warp", "CV-trajectory", "CTR-trajectory", "GT-pose warp (ref.)",
        "GT-pose + object-CV movers (ref.)", "GT-pose warp + GT movers (ref.)",
    ]  # fmt: skip
    saved = json.loads((tmp_path / "eval_metrics.json").read_text())
    n = sum(float(rows["model"][f"{s}_windows"]) for s in ("straight", "turning"))
    assert n == saved["val/num_windows"]
    assert rows["CTR-warp"]["straight_windows"] == rows["model"]["straight_windows"]
    assert float(rows["model"]["miou_1s_pct"]) == pytest.approx(100 * saved["val/model/miou_1s"])
    assert float(rows["CV-trajectory"]["l2_mean_to_horizon_2s_m"]) == pytest.approx(
        saved["val/cv_traj/l2_mean_to_horizon_2s"]
    )
    assert rows["CV-trajectory"]["miou_1s_pct"] == ""  # not applicable: left empty
    assert rows["Copy&Paste"]["l2_at_horizon_avg_m"] == ""
    md = (tmp_path / "world_model_eval.md").read_text()
    assert "| 3D-Occ | model |" in md and "| 3D-Occ | CV-warp |" in md and "OccWorld protocol" in md
    assert "–: not applicable" in md  # the dashes are explained under the table
    for name in ("bev_forecast.png", "bev_movers.png", "trajectories.png"):  # its pictures
        assert (tmp_path / name).stat().st_size > 5_000


def test_eval_takes_the_architecture_from_the_checkpoint(trained, wm_overrides, tmp_path):
    run, metrics = trained
    ckpt = f"ckpt={run / 'checkpoints' / 'last.pt'}"
    default_arch = [o for o in wm_overrides if o not in TINY_MODEL]
    cfg = compose_cfg([*default_arch, ckpt, f"run_dir={tmp_path / 'a'}"], "eval")
    with pytest.warns(UserWarning, match=r"stage\.model: embed_dim=16 \(not 128\)"):
        again = evaluate(cfg)
    assert again["val/model/miou_1s"] == pytest.approx(metrics["val/model/miou_1s"], rel=1e-9)
    cfg = compose_cfg([*wm_overrides, ckpt, f"run_dir={tmp_path / 'b'}", "stage.future=2"], "eval")
    with pytest.raises(ValueError, match=r"stage\.future: the checkpoint .* trained with 4"):
        evaluate(cfg)


def test_tokenizer_checkpoint_errors_name_the_key(wm_overrides, tmp_path, tokenizer_ckpt):
    base = [o for o in wm_overrides if not o.startswith("stage.tokenizer_ckpt=")]
    with pytest.raises(ValueError, match=r"stage\.tokenizer_ckpt: required config value"):
        train(compose_cfg([*base, f"run_dir={tmp_path / 'a'}"]))
    with pytest.raises(ValueError, match=r"stage\.tokenizer_ckpt: required config value"):
        evaluate(compose_cfg([*base, f"run_dir={tmp_path / 'b'}", "ckpt=x.pt"], "eval"))
    with pytest.raises(CheckpointError, match=r"stage\.tokenizer_ckpt: .*no such file"):
        train(compose_cfg([*base, f"run_dir={tmp_path / 'c'}", "stage.tokenizer_ckpt=nope.pt"]))
    with pytest.raises(ValueError, match=r"stage\.tokenizer_ckpt: .*grid 'quarter'"):
        train(compose_cfg([*wm_overrides, f"run_dir={tmp_path / 'd'}", "grid=quarter"]))
    with pytest.raises(ValueError, match=r"stage\.model\.codebook_sizes: set by the tokenizer"):
        train(compose_cfg([*wm_overrides, f"run_dir={tmp_path / 'e'}",
                           "+stage.model.codebook_sizes=[4,4]"]))  # fmt: skip
    with pytest.raises(ValueError, match=r"stage\.history: expected an int >= 2"):
        train(compose_cfg([*wm_overrides, f"run_dir={tmp_path / 'f'}", "stage.history=1"]))
    assert not any((tmp_path / d).exists() for d in "abcdef"), "nothing written on failure"


def test_planner_bundle_round_trip(trained, tokenizer_ckpt, converted, tmp_path):
    run, _ = trained
    ckpt = run / "checkpoints" / "last.pt"
    out = export_planner_bundle(ckpt, tokenizer_ckpt, tmp_path / "planner.pt")
    planner = load_planner(out)
    root, infos = converted
    window = OccSequenceDataset(load_infos(infos, "val"), root, history=5, future=0)[0]
    req = PlanRequest(window["occ"].numpy(), window["ego_displacements"].numpy(), "straight")
    res = planner.plan(req)
    assert res.trajectory.shape == (FUTURE, 2) and np.isfinite(res.trajectory).all()
    assert res.occupancy_forecast.shape == (FUTURE, 50, 50, 4)
    # Same numbers as the stage's own model and tokenizer on the last HISTORY frames.
    tok = _load_tok(tokenizer_ckpt)
    model = WorldModel(planner.config)
    model.load_state_dict(load_checkpoint(ckpt)["model"], strict=True)
    idx = tok.encode(window["occ"][-HISTORY:]).indices[None]
    ro = model.eval().rollout(idx, window["ego_displacements"][None, -(HISTORY - 1) :],
                              torch.tensor([2]), steps=FUTURE)  # fmt: skip
    np.testing.assert_allclose(res.trajectory, ro.trajectory[0].numpy(), rtol=1e-5, atol=1e-5)
    # A tokenizer file other than the one trained on is flagged.
    other = tmp_path / "copy.pt"
    shutil.copy(tokenizer_ckpt, other)
    with pytest.warns(UserWarning, match="differs from the tokenizer"):
        export_planner_bundle(ckpt, other, tmp_path / "planner2.pt")


def _load_tok(path):
    from renderworld.training.stages.tokenizer import load_tokenizer

    return load_tokenizer(path)


def test_mini_experiment_builds_the_model_it_names(converted, tokenizer_ckpt, tmp_path):
    """experiment=world_model_mini (the main job's) trains the pose-warp model with the blended
    CTR / CV pose anchors at its own size and window; the stage's defaults build another."""
    from renderworld.world.pose import PoseWarpWorldModel

    tok = f"stage.tokenizer_ckpt={tokenizer_ckpt}"
    mini = compose_cfg(["experiment=world_model_mini", tok, f"run_dir={tmp_path}"])
    plain = compose_cfg(["stage=world_model", "grid=coarse", tok, f"run_dir={tmp_path}"])
    model = WorldModelStage(mini).build_model(mini)
    default = WorldModelStage(plain).build_model(plain)
    assert isinstance(model, PoseWarpWorldModel) and model.pose.anchors == "ctr_cv"
    assert type(default) is WorldModel
    built = (model.config.embed_dim, model.config.history_frames, model.config.future_frames)
    assert built == (mini.stage.model.embed_dim, mini.stage.history, mini.stage.future)
    assert model.config.embed_dim != default.config.embed_dim


def test_camera_setting_scores_pseudo_label_inputs_against_gt(converted, tmp_path):
    from renderworld.constants import FREE_ID
    from renderworld.data import load_occ3d_labels, save_occ3d_labels
    from renderworld.training.stages.world_model.windows import WorldModelWindows

    root, infos_dir = converted
    infos = load_infos(infos_dir, "val")
    pseudo = tmp_path / "pseudo"
    for scene, token, occ_path in zip(
        infos["scene_name"], infos["sample_token"], infos["occ_path"], strict=True
    ):
        gt = load_occ3d_labels(root / occ_path)
        free = np.full_like(gt.semantics, FREE_ID)  # a pseudo labeller that sees nothing
        save_occ3d_labels(
            pseudo / scene / token / "labels.npz", free, gt.mask_lidar, gt.mask_camera
        )
    cam = WorldModelWindows(infos, root, "coarse", 3, 2, occ_root=pseudo, gt_targets=True)
    gt_only = OccSequenceDataset(infos, root, history=3, future=2, grid="coarse")
    item = cam[0]
    assert (item["occ"] == FREE_ID).all()  # inputs: pseudo labels
    assert torch.equal(item["occ_target"], gt_only[0]["occ"])  # targets: GT
    assert (item["occ_target"] != FREE_ID).any()
    # Without gt_targets (training windows) nothing extra is loaded.
    assert "occ_target" not in WorldModelWindows(infos, root, "coarse", 3, 2, occ_root=pseudo)[0]


def _pseudo_labels(converted, out, free: bool):
    """Pseudo labels in the export layout: the GT itself, or all free (a labeller that sees
    nothing)."""
    from renderworld.constants import FREE_ID
    from renderworld.data import load_occ3d_labels, save_occ3d_labels

    root, infos_dir = converted
    for split in ("train", "val"):
        infos = load_infos(infos_dir, split)
        for scene, token, occ_path in zip(
            infos["scene_name"], infos["sample_token"], infos["occ_path"], strict=True
        ):
            gt = load_occ3d_labels(root / occ_path)
            sem = np.full_like(gt.semantics, FREE_ID) if free else gt.semantics
            save_occ3d_labels(
                out / scene / token / "labels.npz", sem, gt.mask_lidar, gt.mask_camera
            )
    return out


def test_one_eval_scores_both_settings_in_one_table(trained, wm_overrides, converted, tmp_path):
    run, _ = trained
    ckpt = run / "checkpoints" / "last.pt"
    same = _pseudo_labels(converted, tmp_path / "same", free=False)
    cfg = compose_cfg([*wm_overrides, f"ckpt={ckpt}", f"run_dir={tmp_path / 'a'}",
                       f"pseudo_labels={same}", f"camera_ckpt={ckpt}"], "eval")  # fmt: skip
    m = evaluate(cfg)
    # Pseudo labels equal to GT and the same model: the Camera rows equal the 3D-Occ rows.
    names = [k for k in m if k.startswith("val/") and not k.startswith("val/camera/")]
    scored = [k for k in names if "/" in k[4:]]
    assert scored and all(f"val/camera/{k[4:]}" in m for k in scored)
    for k in scored:
        assert m[f"val/camera/{k[4:]}"] == pytest.approx(m[k], rel=1e-9, nan_ok=True), k
    rows = list(csv.DictReader((tmp_path / "a" / "world_model_eval.csv").open()))
    assert [r["setting"] for r in rows] == ["3D-Occ"] * 11 + ["Camera"] * 11
    assert (
        "Camera = Img2Occ pseudo-label inputs"
        in (tmp_path / "a" / "world_model_eval.md").read_text()
    )

    # All-free pseudo labels: the Camera baselines forecast nothing, the 3D-Occ ones are as
    # before; the default Camera model is the ckpt's (no camera_ckpt).
    free = _pseudo_labels(converted, tmp_path / "free", free=True)
    cfg = compose_cfg([*wm_overrides, f"ckpt={ckpt}", f"run_dir={tmp_path / 'b'}",
                       f"pseudo_labels={free}"], "eval")  # fmt: skip
    m2 = evaluate(cfg)
    assert m2["val/copy_paste/miou_1s"] == pytest.approx(m["val/copy_paste/miou_1s"], rel=1e-12)
    assert m2["val/model/miou_1s"] == pytest.approx(m["val/model/miou_1s"], rel=1e-12)
    assert m2["val/camera/copy_paste/iou_1s"] == 0.0  # all free vs GT with occupied voxels
    assert m2["val/camera/cv_traj/l2_at_horizon_1s"] == pytest.approx(
        m["val/cv_traj/l2_at_horizon_1s"]  # trajectories do not depend on occupancy
    )
    for name in ("bev_forecast.png", "bev_movers.png"):
        assert (tmp_path / "b" / name).stat().st_size > 5_000


def test_eval_only_keys_are_rejected_where_they_do_not_apply(wm_overrides, tmp_path):
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}", f"camera_ckpt={tmp_path}"], "eval")
    cfg.ckpt = str(tmp_path / "missing.pt")
    with pytest.raises(ValueError, match="camera_ckpt: .* needs pseudo_labels="):
        WorldModelStage(cfg)


def _readme_blocks(section: str) -> dict[str, str]:
    text = (REPO / "README.md").read_text()
    body = text.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    blocks = {}
    for chunk in body.split("```")[1::2]:
        lang, code = chunk.split("\n", 1)
        blocks[lang.strip()] = code
    return blocks


def test_readme_planner_example_runs(trained, tokenizer_ckpt, tmp_path):
    """The README's planner example, as written: bundle two checkpoints, then plan."""
    run, _ = trained
    blocks = _readme_blocks("Planner API")
    assert set(blocks) == {"bash", "python"}
    export = blocks["bash"].replace("\\\n", " ").strip()
    # Either form: the export function (python -c ...) or the main job's tool.
    assert export.startswith(("python -c ", "python tools/export_planner.py "))
    export = export.replace("python tools/", f"python {REPO}/tools/", 1)
    models = (
        "outputs/wm_tokens/checkpoints/last.pt",
        "outputs/demo/world_model/checkpoints/last.pt",
    )
    assert sum(m in export for m in models) == 1
    for demo, real in (
        *((m, run / "checkpoints" / "last.pt") for m in models if m in export),
        ("outputs/demo/tokenizer/checkpoints/last.pt", tokenizer_ckpt),
    ):
        assert demo in export
        export = export.replace(demo, str(real))
    (tmp_path / "outputs").mkdir()
    env = subprocess_env()
    proc = subprocess.run(
        ["bash", "-c", f"{PYTHON} {export[len('python ') :]}"], cwd=tmp_path, env=env,
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "outputs" / "planner.pt").is_file()
    proc = subprocess.run(
        [PYTHON, "-c", blocks["python"]], cwd=tmp_path, env=env, capture_output=True,
        text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == FUTURE + 1  # FUTURE trajectory rows, then shape and time
    assert lines[-1].startswith(f"({FUTURE}, 50, 50, 4) ")


def test_other_stages_reject_the_world_model_eval_keys(converted, tokenizer_ckpt, tmp_path):
    cfg = compose_cfg(["stage=tokenizer", *_data(converted), f"ckpt={tokenizer_ckpt}",
                       f"run_dir={tmp_path}", f"pseudo_labels={tmp_path}"], "eval")  # fmt: skip
    with pytest.raises(ValueError, match=r"pseudo_labels: only stage=world_model reads it"):
        evaluate(cfg)


@pytest.fixture(scope="module")
def other_tokenizer_ckpt(converted, tmp_path_factory):
    """A second tiny tokenizer with the same codebooks and latent grid, other weights (seed 1)."""
    return _tiny_tokenizer(converted, tmp_path_factory.mktemp("tok2") / "run", "seed=1")


def test_token_cache_separates_tokenizers(wm_overrides, other_tokenizer_ckpt, tmp_path):
    stage, _, train_set, _ = _stage_and_model(wm_overrides, tmp_path)
    batch = next(iter(DataLoader(train_set, batch_size=2)))
    cpu = torch.device("cpu")
    main = stage.window_tokens(batch, HISTORY, cpu)
    other = stage.window_tokens(batch, HISTORY, cpu, tokenizer=str(other_tokenizer_ckpt))
    tok2 = stage.tokenizer_of(str(other_tokenizer_ckpt))
    direct = tok2.encode(batch["occ"][:, :HISTORY].flatten(0, 1)).indices.view(other.shape)
    assert torch.equal(other, direct), "same source and samples, other tokenizer: re-encoded"
    assert not torch.equal(main, other)
    assert torch.equal(stage.window_tokens(batch, HISTORY, cpu), main)


def test_camera_tokenizer_changes_only_the_camera_rows(
    trained, wm_overrides, converted, tokenizer_ckpt, other_tokenizer_ckpt, tmp_path
):
    run, _ = trained
    ckpt = run / "checkpoints" / "last.pt"
    pseudo = _pseudo_labels(converted, tmp_path / "pseudo", free=False)
    base = [*wm_overrides, f"ckpt={ckpt}", f"pseudo_labels={pseudo}", f"camera_ckpt={ckpt}"]
    today = evaluate(compose_cfg([*base, f"run_dir={tmp_path / 'a'}"], "eval"))
    # The 3D-Occ tokenizer passed explicitly: today's results, key for key.
    same = evaluate(compose_cfg([*base, f"run_dir={tmp_path / 'b'}",
                                 f"camera_tokenizer_ckpt={tokenizer_ckpt}"], "eval"))  # fmt: skip
    assert same.keys() == today.keys()
    for k, v in today.items():
        assert same[k] == pytest.approx(v, rel=1e-12, nan_ok=True), k
    # Another tokenizer: the Camera model rows change, the 3D-Occ rows and the Camera
    # baselines (no tokenizer) do not; the model was trained on the first tokenizer: a warning.
    with pytest.warns(UserWarning, match=r"camera_tokenizer_ckpt: .* differs from the tokenizer"):
        other_tok = f"camera_tokenizer_ckpt={other_tokenizer_ckpt}"
        other = evaluate(compose_cfg([*base, f"run_dir={tmp_path / 'c'}", other_tok], "eval"))
    for k, v in today.items():
        if not k.startswith("val/camera/"):
            assert other[k] == pytest.approx(v, rel=1e-12, nan_ok=True), k
    for k in ("copy_paste/miou_1s", "warp_cv/miou_1s", "cv_traj/l2_at_horizon_1s"):
        assert other[f"val/camera/{k}"] == pytest.approx(today[f"val/camera/{k}"], rel=1e-12)
    changed = [
        k for k in today
        if k.startswith("val/camera/model/miou_step") and other[k] != pytest.approx(today[k])
    ]  # fmt: skip
    assert changed, "the Camera forecasts are encoded and decoded with the other tokenizer"
    md = (tmp_path / "c" / "world_model_eval.md").read_text()
    assert f"tokenizer = {other_tokenizer_ckpt} (camera_tokenizer_ckpt)" in md
    assert f"3D-Occ = GT occupancy inputs, GT targets, tokenizer = {tokenizer_ckpt}" in md
    md = (tmp_path / "a" / "world_model_eval.md").read_text()
    assert f"tokenizer = {tokenizer_ckpt} (the 3D-Occ tokenizer; no camera_tokenizer_ckpt)" in md


def test_camera_tokenizer_errors_name_the_key(wm_overrides, tokenizer_ckpt, tmp_path):
    tok = f"camera_tokenizer_ckpt={tokenizer_ckpt}"
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}", "ckpt=x.pt", tok], "eval")
    with pytest.raises(ValueError, match=r"camera_tokenizer_ckpt: .* needs pseudo_labels="):
        WorldModelStage(cfg)
    cfg = compose_cfg([*wm_overrides, f"run_dir={tmp_path}", "ckpt=x.pt",
                       f"pseudo_labels={tmp_path}",
                       f"camera_tokenizer_ckpt={tmp_path / 'no.pt'}"], "eval")  # fmt: skip
    with pytest.raises(ValueError, match=r"camera_tokenizer_ckpt: .*no\.pt' does not exist"):
        WorldModelStage(cfg)
