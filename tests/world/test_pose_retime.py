"""The plan retimed along its own path: the leader changes how far the ego gets, not where."""

from __future__ import annotations

import math

import pytest
import torch

from renderworld.constants import GridSpec
from renderworld.world.pose_retime import LeaderRetiming, retime_along_path

#: 1.6 m cells over +-40 m: the coarse grid's reach.
GRID = GridSpec("test-lead", (-40.0, -40.0, -1.0), (40.0, 40.0, 3.0), (50, 50, 2))


def _arc(radius=20.0, step=2.0, n=6):
    """[n, 3] poses along a left arc, ``step`` metres apart."""
    phi = torch.arange(1, n + 1, dtype=torch.float64) * step / radius
    return torch.stack([radius * torch.sin(phi), radius * (1 - torch.cos(phi)), phi], -1)


def test_factor_one_keeps_the_plan_and_a_half_moves_halfway_along_it():
    path = _arc()
    torch.testing.assert_close(retime_along_path(path, torch.ones(6, dtype=path.dtype)), path)
    half = retime_along_path(path, torch.full((6,), 0.5, dtype=path.dtype))
    # Step 2 goes where step 1 was, step 4 where step 2 was: along the path, headings with it.
    torch.testing.assert_close(half[1], path[0])
    torch.testing.assert_close(half[3], path[1])
    # Between poses: on the chord, the heading between theirs.
    torch.testing.assert_close(half[0], path[0] / 2)


def test_a_stop_a_speed_up_and_the_pi_cut():
    straight = torch.tensor([[2.0, 0, 0], [4, 0, 0], [6, 0, 0]])
    stop = retime_along_path(straight, torch.tensor([1.0, 0.5, 0.0]))
    torch.testing.assert_close(stop, torch.tensor([[2.0, 0, 0], [2, 0, 0], [0, 0, 0]]))
    fast = retime_along_path(straight, torch.full((3,), 1.5))  # beyond the end: carried on
    torch.testing.assert_close(fast[:, 0], torch.tensor([3.0, 6.0, 9.0]))
    # A path whose heading crosses +-pi (driving backwards and turning) interpolates the short way.
    back = torch.tensor([[-2.0, 0.0, math.pi - 0.1], [-4.0, 0.0, -math.pi + 0.1]])
    mid = retime_along_path(back, torch.tensor([1.0, 0.625]))  # a quarter of the way on
    assert mid[1, 2].item() == pytest.approx(math.pi - 0.05, abs=1e-5)


def test_degenerate_plans_stay_finite_forward_and_backward():
    for poses in (torch.zeros(2, 4, 3), torch.tensor([[[1.0, 0, 0], [1, 0, 0], [1, 0, 0]]])):
        poses = poses.clone().requires_grad_(True)
        f = torch.full(poses.shape[:-1], 0.7, requires_grad=True)
        out = retime_along_path(poses, f)
        out.square().sum().backward()
        assert torch.isfinite(out).all() and torch.isfinite(poses.grad).all()
        assert torch.isfinite(f.grad).all()
    still = torch.zeros(1, 3, 3)
    torch.testing.assert_close(retime_along_path(still, torch.full((1, 3), 0.3)), still)
    with pytest.raises(ValueError, match="poses/factors: expected"):
        retime_along_path(torch.zeros(2, 3, 3), torch.ones(2, 4))


def test_the_module_starts_at_one_and_learns_from_the_leader():
    torch.manual_seed(0)
    mod = LeaderRetiming(history=5, steps=6, leader_in=10)
    hist, cmd = torch.randn(2, 20), torch.eye(3)[:2]
    lead = torch.zeros(2, 10)
    torch.testing.assert_close(mod(hist, cmd, lead), torch.ones(2, 3, 6))
    with torch.no_grad():
        mod.mlp[-1].weight.normal_()
    braking = lead.clone()
    braking[:, :4] = torch.tensor([1.0, 0.4, 0.5, 0.1])
    a, b = mod(hist, cmd, lead), mod(hist, cmd, braking)
    assert (a > 0).all() and not torch.allclose(a, b)


def test_the_pose_head_with_a_leader_keeps_its_path_and_changes_its_progress():
    from renderworld.world.pose import PoseHead
    from renderworld.world.pose_agents import LEADER_FEATURES

    torch.manual_seed(0)
    head = PoseHead(history=5, steps=6, bev_in=7, leader=True)
    with torch.no_grad():
        head.mlp[-1].weight.normal_(std=0.1)
    t = torch.arange(-4, 1, dtype=torch.float32) * 0.5
    hist = torch.stack([8.0 * t, 0.02 * t**2, 0.01 * t], -1)[None]
    cmd, bev = torch.tensor([0]), torch.rand(1, 7, 32, 32)
    lead = torch.zeros(1, LEADER_FEATURES)
    base, _ = head(hist, cmd, bev, lead)
    with torch.no_grad():
        head.retime.mlp[-1].bias.fill_(-0.5)  # every step 0.61 of the way
    slow, _ = head(hist, cmd, bev, lead)
    assert (slow[0, :, 0] < base[0, :, 0]).all()
    # Every slowed pose lies on the plan's own polyline.
    pts = torch.cat([torch.zeros(1, 2), base[0, :, :2]])
    a, b = pts[:-1], pts[1:]
    for p in slow[0, :, :2]:
        u = ((p - a) * (b - a)).sum(-1) / (b - a).square().sum(-1)
        near = a + u.clamp(0, 1)[:, None] * (b - a)
        assert (near - p).norm(dim=-1).min() < 1e-4
    with pytest.raises(ValueError, match="leader=True"):
        head(hist, cmd, bev)


def _lead(centroid, v_now, decel, half_length=2.3):
    """A car in the ego's lane at ``centroid`` moving at ``v_now`` m/s along x, braking at
    ``decel`` m/s² over the whole 2 s history; its cells span ``half_length`` either side."""
    import numpy as np

    from renderworld.world.tracks import MoverTrack
    from tests.world.test_movers import CAR

    t = np.array([0.0, -0.5, -1.0, -1.5, -2.0])
    x = centroid[0] + v_now * t - 0.5 * decel * t**2  # earlier: faster when braking
    cents = np.stack([x, np.full_like(x, centroid[1])], 1)
    cells = np.zeros(GRID.shape[:2], bool)
    lo = GRID.range_min[0]
    for xx in np.arange(centroid[0] - half_length + 0.8, centroid[0] + half_length, 1.6):
        cells[int((xx - lo) // 1.6), int((centroid[1] - GRID.range_min[1]) // 1.6)] = True
    vel = np.polyfit(t, cents, 1)[0]
    return MoverTrack(CAR, cells, np.asarray(centroid, float), t, cents, vel, True)


def test_a_plan_stops_behind_a_lead_car_braking_hard_and_nothing_else_changes():
    import numpy as np

    from renderworld.constants import EGO_CENTRE_OFFSET, EGO_LENGTH
    from renderworld.world.pose_retime import leader_stop_factors, stop_profile

    hist = np.stack([10.0 * np.arange(-4, 1) * 0.5, np.zeros(5), np.zeros(5)], 1)  # 10 m/s
    plan = np.stack([10.0 * np.arange(1, 7) * 0.5, np.zeros(6), np.zeros(6)], 1)  # goes on
    braking = _lead((16.0, 0.0), v_now=6.0, decel=4.0)
    f = leader_stop_factors(plan, [braking], hist, GRID)
    s = f * plan[:, 0]
    assert (f < 1).all() and np.all(np.diff(s) >= -1e-9)
    # It stops where the lead car will stand (6² / 8 = 4.5 m on), 2 m behind its rear.
    rear = braking.cells.nonzero()[0].min() * 1.6 + GRID.range_min[0]
    room = rear + 4.5 - 2.0 - (EGO_CENTRE_OFFSET + EGO_LENGTH / 2)
    assert s[-1] == pytest.approx(room, abs=1e-6)
    np.testing.assert_allclose(s, stop_profile(plan[:, 0], 10.0, room, 0.5))
    # A lead car keeping its speed, one braking gently, one far enough ahead, a parked car, one
    # in the next lane: the plan is left alone.
    cruise = _lead((16.0, 0.0), v_now=10.0, decel=0.0)
    gentle = _lead((16.0, 0.0), v_now=9.0, decel=1.0)
    far = _lead((38.0, 0.0), v_now=6.0, decel=4.0)
    beside = _lead((16.0, 3.5), v_now=6.0, decel=4.0)
    parked = _lead((16.0, 0.0), v_now=0.0, decel=0.0)
    parked.moving = False
    for other in (cruise, gentle, far, beside, parked):
        np.testing.assert_array_equal(leader_stop_factors(plan, [other], hist, GRID), 1.0)
    # One that has come to a stand after moving counts; no room at all: the ego stands.
    stood = _lead((7.0, 0.0), v_now=0.0, decel=4.0)
    np.testing.assert_array_equal(leader_stop_factors(plan, [stood], hist, GRID), 0.0)
    np.testing.assert_array_equal(stop_profile(np.ones(3), 5.0, -1.0, 0.5), 0.0)


def _mover(centroid, velocity, half_length=2.3, cls=None):
    """A road user at ``centroid`` that moved at a constant ``velocity`` [2] m/s over the 2 s
    history; its cells span ``half_length`` either side along x (one cell: a pedestrian)."""
    import numpy as np

    from renderworld.world.tracks import MoverTrack
    from tests.world.test_movers import CAR

    t = np.array([0.0, -0.5, -1.0, -1.5, -2.0])
    cents = np.asarray(centroid, float)[None] + t[:, None] * np.asarray(velocity, float)[None]
    cells = np.zeros(GRID.shape[:2], bool)
    iy = int((centroid[1] - GRID.range_min[1]) // 1.6)
    for xx in np.arange(centroid[0] - half_length + 0.8, centroid[0] + half_length, 1.6):
        cells[int((xx - GRID.range_min[0]) // 1.6), iy] = True
    vel = np.asarray(velocity, float)
    return MoverTrack(CAR if cls is None else cls, cells, np.asarray(centroid, float), t, cents,
                      vel, True)  # fmt: skip


def test_a_car_crossing_or_coming_the_other_way_is_no_leader_that_stood():
    import numpy as np

    from renderworld.world.pose_retime import leader_stop_factors

    hist = np.stack([10.0 * np.arange(-4, 1) * 0.5, np.zeros(5), np.zeros(5)], 1)
    plan = np.stack([10.0 * np.arange(1, 7) * 0.5, np.zeros(6), np.zeros(6)], 1)
    crossing = _mover((14.0, 0.5), (0.0, 8.0))  # across the lane ahead at 8 m/s
    oncoming = _mover((20.0, 0.5), (-9.0, 0.0))
    for other in (crossing, oncoming):
        np.testing.assert_array_equal(leader_stop_factors(plan, [other], hist, GRID), 1.0)


def test_a_plan_slows_for_a_car_cutting_in_and_stops_for_a_pedestrian_stepping_in():
    import numpy as np

    from renderworld.constants import EGO_CENTRE_OFFSET, EGO_LENGTH
    from renderworld.world.pose_retime import leader_stop_factors, stop_profile
    from tests.world.test_movers import PED

    front = EGO_CENTRE_OFFSET + EGO_LENGTH / 2
    hist = np.stack([10.0 * np.arange(-4, 1) * 0.5, np.zeros(5), np.zeros(5)], 1)  # 10 m/s
    plan = np.stack([10.0 * np.arange(1, 7) * 0.5, np.zeros(6), np.zeros(6)], 1)
    # A car 14 m ahead in the next lane (3.2 m left) at 5 m/s, drifting in at 1 m/s: its
    # centroid enters the corridor (2 m to each side) after 1.25 s, 20.25 m ahead.
    cut_in = _mover((14.0, 3.2), (5.0, -1.0))
    rear = cut_in.cells.nonzero()[0].min() * 1.6 + GRID.range_min[0]
    f = leader_stop_factors(plan, [cut_in], hist, GRID, entering=True)
    room = rear - 2.0 - front  # behind its rear, moving on at 5 m/s: the ego slows to 5 m/s
    np.testing.assert_allclose(f * plan[:, 0], stop_profile(plan[:, 0], 10.0, room, 0.5, 5.0))
    s = f * plan[:, 0]
    assert (f < 1).any() and np.all(np.diff(s) >= -1e-9)
    assert s[-1] - s[-2] == pytest.approx(2.5)  # 5 m/s in the last half second
    np.testing.assert_array_equal(leader_stop_factors(plan, [cut_in], hist, GRID), 1.0)  # off
    # A pedestrian 18 m ahead walking in from the kerb at 1.4 m/s: the plan stops before it.
    ped = _mover((18.0, -3.5), (0.0, 1.4), half_length=0.8, cls=PED)
    s = leader_stop_factors(plan, [ped], hist, GRID, entering=True) * plan[:, 0]
    ped_rear = ped.cells.nonzero()[0].min() * 1.6 + GRID.range_min[0]
    assert s[-1] == pytest.approx(ped_rear - 2.0 - front, abs=1e-6)
    # The same car driving on in its own lane, one cutting in behind the ego, one faster than
    # the ego, a pedestrian walking along the kerb: nothing changes.
    parallel = _mover((14.0, 3.2), (5.0, 0.0))
    behind = _mover((-8.0, 3.2), (5.0, -1.0))
    faster = _mover((14.0, 3.2), (14.0, -1.0))
    along = _mover((18.0, -3.5), (1.4, 0.0), half_length=0.8, cls=PED)
    # One stepping in 6 m ahead in 1.5 s: the ego (10 m/s) is past it by then, so it goes first.
    passed = _mover((6.0, -3.5), (0.0, 1.4), half_length=0.8, cls=PED)
    for other in (parallel, behind, faster, along, passed):
        f = leader_stop_factors(plan, [other], hist, GRID, entering=True)
        np.testing.assert_array_equal(f, 1.0)


def test_a_stop_profile_behind_a_moving_leader_ends_at_its_speed():
    import numpy as np

    from renderworld.world.pose_retime import stop_profile

    plan = 10.0 * np.arange(1, 7) * 0.5
    # 8 m of room behind a leader at 6 m/s: (10 - 6)² / 16 = 1 m/s² down to 6 m/s by 4 s.
    s = stop_profile(plan, 10.0, 8.0, 0.5, 6.0)
    t = np.arange(1, 7) * 0.5
    np.testing.assert_allclose(s, 10.0 * t - 0.5 * t * t)
    # Slower than the leader, or no room: the ego keeps behind the leader's motion.
    np.testing.assert_allclose(stop_profile(plan, 4.0, 3.0, 0.5, 6.0), np.minimum(plan, 3 + 6 * t))
    np.testing.assert_allclose(stop_profile(plan, 10.0, -2.0, 0.5, 6.0), np.maximum(6 * t - 2, 0))
    # With a leader that stands it is the stop of before.
    np.testing.assert_array_equal(
        stop_profile(plan, 10.0, 8.0, 0.5, 0.0),
        np.minimum(plan, np.where(t < 1.6, 10 * t - 3.125 * t * t, 8)),
    )


def test_the_world_model_stops_its_plan_at_prediction_time_only():
    import numpy as np

    from renderworld.world import WorldModelConfig
    from renderworld.world.pose import PoseWarpWorldModel
    from tests.world.test_movers import _scene

    cfg = WorldModelConfig(
        codebook_sizes=(8,), token_grid=(4, 4), embed_dim=16, num_heads=2, num_scales=1,
        layers_per_scale=(1,), history_frames=5, future_frames=2,
    )  # fmt: skip
    from tests.world.test_movers import GRID as SCENE_GRID

    occ, poses = _scene(ego_step=1)
    hist, hp = torch.from_numpy(occ)[None], torch.from_numpy(poses)[None].float()
    models = {}
    for flag in (False, True):
        torch.manual_seed(0)
        models[flag] = PoseWarpWorldModel(cfg, leader_stop=flag).eval()
    plain, _ = models[False].predict_poses(hp, torch.tensor([1]), hist[:, -1], hist, SCENE_GRID)
    stop, _ = models[True].predict_poses(hp, torch.tensor([1]), hist[:, -1], hist, SCENE_GRID)
    assert torch.equal(stop, plain)  # nobody brakes ahead in this scene: bit for bit
    models[True].train()
    with torch.no_grad():
        trained, _ = models[True].predict_poses(hp, torch.tensor([1]), hist[:, -1])
    torch.testing.assert_close(trained, plain)  # training: the rule is off, no history needed
    with pytest.raises(ValueError, match="history: leader_stop needs"):
        models[True].eval().predict_poses(hp, torch.tensor([1]), hist[:, -1])
    with pytest.raises(ValueError, match="leader_stop: expected true or false"):
        PoseWarpWorldModel(cfg, leader_stop=np.bool_(True))


def test_the_world_model_stops_its_plan_behind_a_car_that_has_just_stood():
    import numpy as np

    from renderworld.world import WorldModelConfig
    from renderworld.world.pose import PoseWarpWorldModel
    from tests.world.test_movers import CAR, _frame
    from tests.world.test_movers import GRID as SCENE_GRID

    cfg = WorldModelConfig(
        codebook_sizes=(8,), token_grid=(4, 4), embed_dim=16, num_heads=2, num_scales=1,
        layers_per_scale=(1,), history_frames=5, future_frames=6,
    )  # fmt: skip
    # The ego drives 1 voxel (1.6 m) per frame along x; a car in its lane (row 15: y = 0.8 m)
    # moved 1 voxel per frame and stands in the current one (world cells, current frame: x =
    # 18, 5.6 m ahead). Each frame in its own ego frame (the ego j voxels back).
    hp = torch.tensor([[[-j * 1.6, 0.0, 0.0] for j in range(4, -1, -1)]])
    models = {}
    for flag in (False, True):
        torch.manual_seed(0)
        models[flag] = PoseWarpWorldModel(cfg, leader_stop=flag).eval()

    def plans(world_x):
        frames = [_frame([(CAR, world_x[4 - j] + j, 15)]) for j in range(4, -1, -1)]
        hist = torch.from_numpy(np.stack(frames))[None]
        return [models[f].predict_poses(hp, torch.tensor([1]), hist[:, -1], hist, SCENE_GRID)[0]
                for f in (False, True)]  # fmt: skip

    plain, stop = plans([15, 16, 17, 18, 18])
    # Untrained: constant turn rate, 1.6 m per step on; the car's rear is 4.8 m ahead, less
    # than the 2 m gap and the ego's front overhang: no room, the plan stands.
    assert plain[0, -1, 0] > 9.0
    torch.testing.assert_close(stop, torch.zeros_like(stop))
    # The same car driving on at 3.2 m/s: the plan is the model's own, bit for bit.
    plain, stop = plans([14, 15, 16, 17, 18])
    assert torch.equal(stop, plain)
