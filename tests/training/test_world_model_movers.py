"""Learned movers (stage.movers=learned): fitted on the training annotations, scored by their
motion, reproduced by the planner bundle; their targets and metrics on hand-made cases."""

import math

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from renderworld.constants import OCC3D_CLASSES, get_grid
from renderworld.training import train
from renderworld.training.stages.world_model.motion import (
    add_motion_stats,
    empty_motion_stats,
    motion_from_stats,
)
from renderworld.training.stages.world_model.mover_fit import mover_targets
from renderworld.training.stages.world_model.report import MODEL_MOVERS
from renderworld.world.mover_head import MoverHead, mirror_inputs, mover_inputs
from renderworld.world.pose import PoseWarpWorldModel
from renderworld.world.tracks import MoverTrack

from . import test_world_model_stage as base
from .conftest import compose_cfg
from .test_world_model_pose import POSE, _requests, base_tok
from .test_world_model_stage import HISTORY

# The stage tests' module fixtures: the tiny fixture, its tiny tokenizer and the overrides.
converted, tokenizer_ckpt, wm_overrides = base.converted, base.tokenizer_ckpt, base.wm_overrides

LEARNED = [*POSE, "stage.movers=learned", "stage.mover_fit_steps=20", "stage.mover_batch=16"]
CAR = OCC3D_CLASSES.index("car")
GRID = get_grid("coarse")


def _track(centroid, cls=CAR) -> MoverTrack:
    cells = np.zeros(GRID.shape[:2], dtype=bool)
    ix = int((centroid[0] + 40) / 1.6)
    iy = int((centroid[1] + 40) / 1.6)
    cells[ix : ix + 2, iy] = True
    c = np.asarray(centroid, dtype=np.float64)
    return MoverTrack(cls, cells, c, np.array([0.0, -0.5]), np.stack([c, c - [2.0, 0.0]]),
                      np.array([4.0, 0.0]), True)  # fmt: skip


def test_targets_follow_the_matched_road_user_by_identity():
    tracks = [_track((10.0, 0.0)), _track((-20.0, 5.0))]
    # Two boxes at t: instance 7 near the first track, instance 3 far from everything.
    cur = np.array([[10.5, 0.2, 4.5, 1.9, 0.0, CAR, 7], [30.0, 9.0, 4.5, 1.9, 0.0, CAR, 3]])
    fut = np.zeros((3, 2, 7))
    fut[:, 0] = [[31.0, 9.0, 4.5, 1.9, 0, CAR, 3]]  # another instance listed first
    fut[:, 1, :2] = [[12.5, 0.2], [14.5, 0.2], [16.5, 0.2]]
    fut[:, 1, 2:] = [4.5, 1.9, 0.0, CAR, 7]
    fmask = np.ones((3, 2), dtype=bool)
    fmask[2, 1] = False  # not annotated at the last step
    disp, valid, inst = mover_targets(tracks, cur, np.ones(2, bool), fut, fmask)
    assert inst.tolist() == [7, -1]  # the second track has no box within reach
    np.testing.assert_allclose(disp[0, :2], [[2.0, 0.0], [4.0, 0.0]])
    assert valid[0].tolist() == [True, True, False] and not valid[1].any()


def test_an_untrained_head_is_constant_velocity_and_mirroring_mirrors():
    occ = np.full((HISTORY, *GRID.shape), 17, dtype=np.uint8)
    occ[..., 0] = OCC3D_CLASSES.index("driveable_surface")
    poses = np.stack([np.arange(-HISTORY + 1, 1) * 5.0, np.zeros(HISTORY), np.zeros(HISTORY)], 1)
    tracks = [_track((10.0, 3.2))]
    inp = mover_inputs(occ[-1], poses, tracks, GRID, 4)
    head = MoverHead(HISTORY, 4)
    out = head(*(torch.from_numpy(a) for a in (inp.feats, inp.patches, inp.base)))
    np.testing.assert_allclose(out.detach().numpy(), inp.base)  # v t at t = 0.5 ... 2 s
    np.testing.assert_allclose(inp.base[0, -1], [8.0, 0.0])
    twice = mirror_inputs(mirror_inputs(inp, HISTORY), HISTORY)
    for a, b in ((twice.feats, inp.feats), (twice.patches, inp.patches), (twice.base, inp.base)):
        np.testing.assert_array_equal(a, b)
    once = mirror_inputs(inp, HISTORY)
    mirrored = [MoverTrack(CAR, tracks[0].cells[:, ::-1], np.array([10.0, -3.2]),
                           tracks[0].times, tracks[0].centroids * [1, -1],
                           np.array([4.0, 0.0]), True)]  # fmt: skip
    direct = mover_inputs(occ[-1], poses, mirrored, GRID, 4)
    np.testing.assert_allclose(once.feats, direct.feats, atol=1e-6)


def test_motion_metrics_count_only_moving_annotated_movers():
    class Still:
        movers = "static"

    occ = torch.full((1, HISTORY, *GRID.shape), 17, dtype=torch.uint8)
    occ[0, :, 30:33, 25, 0] = CAR  # one car in every frame, 4.8 m long
    batch = {
        "occ": occ,
        "history_poses": torch.zeros(1, HISTORY, 3),
        "current_boxes": torch.tensor([[[9.6, 0.8, 4.5, 1.9, 0.0, CAR, 1]]]),
        "current_boxes_mask": torch.ones(1, 1, dtype=torch.bool),
        "future_boxes": torch.tensor(
            [[[9.6 + 3.0 * k, 0.8, 4.5, 1.9, 0, CAR, 1]] for k in range(1, 5)]
        )[None],  # fmt: skip
        "future_boxes_mask": torch.ones(1, 4, 1, dtype=torch.bool),
        "meta": {"scene_description": ["Simulated straight, lead brake, day"]},
    }
    stats = empty_motion_stats(4, "cpu")
    add_motion_stats(stats, Still(), batch, "occ", HISTORY, GRID)
    m = motion_from_stats(stats, (1.0, 2.0))
    # The static model leaves the car where it is: its errors are the car's displacements.
    assert m["motion/model/all/fde_1s"] == pytest.approx(6.0)
    assert m["motion/model/all/fde_2s"] == pytest.approx(12.0)
    assert m["motion/model/all/ade_2s"] == pytest.approx((3 + 6 + 9 + 12) / 4)
    assert m["motion/model/behaviour/lead_brake/movers_2s"] == 1
    assert m["motion/model/class/car/fde_1s"] == pytest.approx(6.0)
    # A car that does not move is not counted.
    batch["future_boxes"][..., 0] = 9.6
    stats = empty_motion_stats(4, "cpu")
    add_motion_stats(stats, Still(), batch, "occ", HISTORY, GRID)
    assert "motion/model/all/fde_1s" not in motion_from_stats(stats, (1.0, 2.0))


def test_learned_movers_train_score_and_plan_as_the_stage_forecasts(wm_overrides, tmp_path):
    from renderworld.planning import load_planner
    from renderworld.planning.scene import head_forecaster, model_forecaster
    from renderworld.training.stages.world_model import WorldModelStage, export_planner_bundle

    run = tmp_path / "run"
    metrics = train(compose_cfg([*wm_overrides, *LEARNED, f"run_dir={run}", "trainer.max_steps=2",
                                 "trainer.val_every=2"]))  # fmt: skip
    assert math.isfinite(metrics[f"val/{MODEL_MOVERS}/movers_miou_1s"])
    assert math.isfinite(metrics["val/motion/model/all/fde_1s"])
    assert math.isfinite(metrics["val/motion/object_cv/all/fde_1s"])
    assert (run / "world_model_motion.csv").is_file()
    ckpt = run / "checkpoints" / "last.pt"
    bundle = export_planner_bundle(ckpt, base_tok(wm_overrides), tmp_path / "planner.pt")
    planner = load_planner(bundle)
    wm = planner.world_model
    assert isinstance(wm, PoseWarpWorldModel) and wm.movers == "learned"
    assert wm.mover_head.mlp[-1].weight.abs().sum() > 0  # fitted: no longer constant velocity
    assert model_forecaster(wm).__qualname__ == head_forecaster(wm.mover_head).__qualname__
    # The planner's forecast and plan are the stage's, movers included.
    stage = WorldModelStage(compose_cfg([*wm_overrides, *LEARNED, f"run_dir={tmp_path / 'e'}"]))
    _, val_set = stage.build_datasets(stage.cfg)
    batch = next(iter(DataLoader(val_set, batch_size=2)))
    fc, traj = stage.forecast(wm, batch, stage.eval_settings[0], None)
    res = planner.plan_batch(_requests(batch, 2))
    for i, r in enumerate(res):
        np.testing.assert_array_equal(r.trajectory, traj["model"][i].numpy())
        np.testing.assert_array_equal(r.occupancy_forecast, fc["model"][i].numpy())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_learned_movers_fit_and_train_on_cuda(wm_overrides, tmp_path):
    """The mover head is fitted on the run's device (it once read CPU tensors into CUDA weights)."""
    cuda = ["trainer.device=cuda", "trainer.precision=bf16"]
    metrics = train(compose_cfg([*wm_overrides, *LEARNED, *cuda, f"run_dir={tmp_path}",
                                 "trainer.max_steps=2", "trainer.val_every=2"]))  # fmt: skip
    assert math.isfinite(metrics[f"val/{MODEL_MOVERS}/movers_miou_1s"])
    assert math.isfinite(metrics["val/motion/model/all/fde_1s"])


def test_behaviour_pictures_take_the_second_window_of_the_first_scene():
    from renderworld.training.stages.world_model.pictures import behaviour_windows

    def item(scene, behaviour):
        return {"meta": {"scene": scene,
                         "scene_description": f"Simulated straight, {behaviour}, day"}}  # fmt: skip

    val = [item("s1", "cruise"), item("s2", "cut in"), item("s2", "cut in"), item("s2", "cut in"),
           item("s3", "lead brake"), item("s4", "cut in"), item("s4", "cut in")]  # fmt: skip
    assert behaviour_windows(val) == {"cut_in": 2, "lead_brake": 4}  # s3 holds one window
    assert behaviour_windows([{"meta": {"scene": "x", "scene_description": "Night"}}]) == {}
