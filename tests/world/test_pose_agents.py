"""What the pose head reads of the other road users: tracked positions and velocities."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import KEYFRAME_DT
from renderworld.world import WorldModelConfig
from renderworld.world.pose import PoseHead, PoseWarpWorldModel
from renderworld.world.pose_agents import AGENT_FEATURES, agent_features, agent_rows
from renderworld.world.tracks import MoverTrack
from tests.world.test_movers import CAR, GRID, PED, VOX, _scene


def _track(cls, centroid, velocity, times=(0.0, -0.5, -1.0, -1.5, -2.0), brake=0.0):
    t = np.array(times)
    v = np.asarray(velocity, dtype=float)
    # Positions of a mover at ``velocity`` now that braked at ``brake`` m/s^2 along it.
    cents = np.asarray(centroid) + t[:, None] * v - 0.5 * brake * (t**2)[:, None] * np.sign(v)
    moving = bool(np.any(v) or brake)
    return MoverTrack(cls, np.zeros((2, 2), bool), np.asarray(centroid, float), t, cents,
                      np.polyfit(t, cents, 1)[0] if moving else np.zeros(2), moving)  # fmt: skip


def test_agent_rows_nearest_first_padded_and_parked_cars_stand():
    far = _track(CAR, (30.0, 0.0), (8.0, 0.0))
    near = _track(PED, (4.0, -3.0), (0.0, 1.2))
    parked = _track(CAR, (10.0, 4.0), (0.0, 0.0))
    rows = agent_rows([far, near, parked], k=4)
    assert rows.shape == (4, AGENT_FEATURES) and rows.dtype == np.float32
    np.testing.assert_allclose(rows[0], [0.2, -0.15, 0.0, 0.12, 0.0, 0.12, 1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(rows[1], [0.5, 0.2, 0, 0, 0, 0, 0.0, 1.0])  # parked: no speed
    np.testing.assert_allclose(rows[2, :2], [1.5, 0.0])
    assert not rows[3].any()  # padding: not present
    assert agent_rows([far, near], k=1).shape == (1, AGENT_FEATURES)


def test_agent_rows_tell_a_braking_lead_car_from_a_cruising_one():
    cruise = agent_rows([_track(CAR, (12.0, 0.0), (8.0, 0.0))], k=1)[0]
    brake = agent_rows([_track(CAR, (12.0, 0.0), (4.0, 0.0), brake=3.0)], k=1)[0]
    np.testing.assert_allclose(cruise[2], cruise[4], atol=1e-6)  # steady: both fits agree
    # Braking: the last second's speed is below the whole history's.
    assert brake[4] < brake[2] - 0.05


def test_agent_features_track_a_car_and_mirror_with_the_scene():
    occ, poses = _scene(mover=(16, 10), mover_step=(1, 0), ego_step=0)
    hist = torch.from_numpy(occ)[None].repeat(2, 1, 1, 1, 1)
    hp = torch.from_numpy(poses)[None].repeat(2, 1, 1).float()
    f = agent_features(hist, hp, GRID, k=3)
    assert f.shape == (2, 3 * AGENT_FEATURES) and f.dtype == torch.float32
    rows = f[0].view(3, AGENT_FEATURES)
    # Two cars: the mover (1 voxel per frame along x) is nearer than the parked one.
    speed = VOX / KEYFRAME_DT / 10.0
    torch.testing.assert_close(rows[0, 2:6], torch.tensor([speed, 0.0, speed, 0.0]),
                               atol=1e-4, rtol=0)  # fmt: skip
    assert rows[1, 2:6].abs().sum() == 0 and rows[:2, 7].tolist() == [1.0, 1.0]
    assert rows[2].abs().sum() == 0
    # The mirrored scene (y -> -y): the same agents with y and vy negated.
    m = agent_features(hist.flip(3), hp * torch.tensor([1.0, -1.0, -1.0]), GRID, k=3)
    sign = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, 1.0]).repeat(3)
    torch.testing.assert_close(m[0], f[0] * sign)
    # Cached: asked again, the same values.
    torch.testing.assert_close(agent_features(hist, hp, GRID, k=3), f)
    with pytest.raises(ValueError, match="k: expected an int >= 1"):
        agent_features(hist, hp, GRID, k=0)
    with pytest.raises(ValueError, match="history/history_poses: expected"):
        agent_features(hist, hp[:, :2], GRID, k=2)


def test_pose_head_reads_the_agents_and_refuses_a_request_without_them():
    cfg = WorldModelConfig(
        codebook_sizes=(8,), token_grid=(4, 4), embed_dim=16, num_heads=2, num_scales=1,
        layers_per_scale=(1,), history_frames=5, future_frames=2,
    )  # fmt: skip
    torch.manual_seed(0)
    model = PoseWarpWorldModel(cfg, agents=2)
    assert model.pose.agents == 2
    with torch.no_grad():
        model.pose.mlp[-1].weight.normal_()
    occ, poses = _scene(mover=(16, 10), mover_step=(1, 0), ego_step=0)
    still_occ, _ = _scene(mover=(16, 10), mover_step=(0, 0), ego_step=0)
    hp, cmd = torch.from_numpy(poses)[None].float(), torch.tensor([0])
    moving = torch.from_numpy(occ)[None]
    still = torch.from_numpy(still_occ)[None]
    # The same current frame, a car that moved against one that stood: another plan.
    torch.testing.assert_close(moving[:, -1], still[:, -1])
    a, _ = model.predict_poses(hp, cmd, moving[:, -1], moving, GRID)
    b, _ = model.predict_poses(hp, cmd, still[:, -1], still, GRID)
    assert not torch.equal(a, b)
    with pytest.raises(ValueError, match="history: the pose head reads agents=2"):
        model.predict_poses(hp, cmd, moving[:, -1])
    with pytest.raises(ValueError, match="agents: the head reads 2 agents"):
        model.pose(hp, cmd, torch.zeros(1, 7, *GRID.shape[:2]))
    with pytest.raises(ValueError, match="agents: expected an int >= 0"):
        PoseHead(history=5, steps=2, agents=-1)


def test_pose_ensemble_is_the_mean_of_heads_from_their_own_seeds():
    from renderworld.world.pose_ensemble import PoseEnsemble

    cfg = WorldModelConfig(
        codebook_sizes=(8,), token_grid=(4, 4), embed_dim=16, num_heads=2, num_scales=1,
        layers_per_scale=(1,), history_frames=5, future_frames=2,
    )  # fmt: skip
    models = {}
    for k in (1, 3):
        torch.manual_seed(0)
        models[k] = PoseWarpWorldModel(cfg, movers="learned", pose_heads=k)
    one, three = models[1], models[3]
    # The first member is the one head; the others differ; the rest of the model (the mover
    # head built after the pose heads) is initialised as with one head.
    torch.testing.assert_close(three.pose.members[0].state_dict(), one.pose.state_dict())
    w = [m.bev[0].weight for m in three.pose.members]
    assert not torch.equal(w[0], w[1]) and not torch.equal(w[1], w[2])
    torch.testing.assert_close(three.mover_head.state_dict(), one.mover_head.state_dict())
    with torch.no_grad():
        for m in three.pose.members:
            m.mlp[-1].weight.normal_()
    occ, poses = _scene(ego_step=1)
    hist = torch.from_numpy(occ)[None]
    hp, cmd = torch.from_numpy(poses)[None].float(), torch.tensor([1])
    mean, modes = three.predict_poses(hp, cmd, hist[:, -1], hist, GRID)
    each, each_modes = three.predict_poses(hp, cmd, hist[:, -1], hist, GRID, members=True)
    assert each.shape == (3, 1, 2, 3) and each_modes.shape == (3, *modes.shape)
    torch.testing.assert_close(mean, each.mean(0))
    assert not torch.allclose(each[0], each[1])
    single, _ = one.predict_poses(hp, cmd, hist[:, -1], hist, GRID, members=True)
    assert single.shape == (1, 1, 2, 3)
    with pytest.raises(ValueError, match="members: expected two or more"):
        PoseEnsemble([PoseHead(5, 2)])
    with pytest.raises(ValueError, match="members: their kinematics differ"):
        PoseEnsemble([PoseHead(5, 2), PoseHead(5, 2, kinematics=True)])
    with pytest.raises(ValueError, match="pose_heads: expected an int >= 1"):
        PoseWarpWorldModel(cfg, pose_heads=0)


def test_corridor_coords_follow_the_arc():
    from renderworld.world.pose_agents import corridor_coords

    pts = np.array([[10.0, 1.0], [-3.0, 0.5]])
    s, lat = corridor_coords(pts, 0.0)
    np.testing.assert_allclose(np.stack([s, lat], 1), pts)
    for kappa in (0.05, -0.05):  # a 20 m radius, left and right
        r, phi = 1.0 / kappa, 0.6
        on = np.array([abs(r) * np.sin(phi), r * (1 - np.cos(phi))])  # on the arc, 12 m along
        head = np.sign(kappa) * phi
        inward = on + 1.5 * np.array([-np.sin(head), np.cos(head)]) * np.sign(kappa)
        s, lat = corridor_coords(np.stack([on, inward]), kappa)
        np.testing.assert_allclose(s[0], abs(r) * phi, atol=1e-9)
        np.testing.assert_allclose(lat, [0.0, 1.5 * np.sign(kappa)], atol=1e-9)


def _steady_history(speed=8.0, h=5):
    t = np.arange(-(h - 1), 1) * KEYFRAME_DT
    return np.stack([speed * t, np.zeros(h), np.zeros(h)], 1)


def test_leader_row_names_the_car_ahead_in_the_lane_and_its_braking():
    from renderworld.world.pose_agents import LEADER_FEATURES, leader_row

    hist = _steady_history()
    beside = _track(CAR, (6.0, 3.5), (8.0, 0.0))  # the next lane: not a leader
    far = _track(CAR, (30.0, 0.3), (8.0, 0.0))
    near = _track(CAR, (14.0, -0.4), (5.0, 0.0), brake=3.0)
    row = leader_row([beside, far, near], hist)
    assert row.shape == (LEADER_FEATURES,) and row.dtype == np.float32
    assert row[0] == 1.0 and row[1] == pytest.approx(14.0 / 20.0)
    assert row[3] < row[2] - 0.05  # the last second slower than the whole history: braking
    assert row[4] == pytest.approx(-0.2) and row[5] == 0.0
    assert not row[6:].any()  # nobody enters: the car beside keeps its lane
    parked = leader_row([_track(CAR, (9.0, 0.0), (0.0, 0.0))], hist)
    assert parked[0] == 1.0 and parked[2] == parked[3] == 0.0  # a parked car in the lane leads
    assert not leader_row([], hist).any()


def test_leader_row_foresees_a_pedestrian_stepping_in_and_a_car_cutting_in():
    from renderworld.world.pose_agents import leader_row

    hist = _steady_history()
    ped = _track(PED, (12.0, -5.0), (0.0, 1.3))  # 3 m from the corridor's edge at 1.3 m/s
    row = leader_row([ped], hist)
    assert row[0] == 0.0 and row[6] == 1.0 and row[9] == 1.0
    assert row[7] == pytest.approx(2.5 / 3.0) and row[8] == pytest.approx(12.0 / 20.0)
    away = leader_row([_track(PED, (12.0, -5.0), (0.0, -1.3))], hist)
    assert not away.any()  # walking away from the road
    cut = leader_row([_track(CAR, (10.0, 3.4), (6.0, -1.2))], hist)
    assert cut[6] == 1.0 and cut[7] == pytest.approx(1.25 / 3.0) and cut[9] == 0.0  # 1.4 m
    # The earliest entry wins; a turning ego's corridor bends with it.
    both = leader_row([ped, _track(CAR, (10.0, 3.4), (6.0, -1.2))], hist)
    np.testing.assert_allclose(both[6:], cut[6:])
    turn = hist.copy()
    turn[-2] = (-4.0 * np.cos(0.05), -4.0 * np.sin(0.05), -0.1)  # turning left: 0.025 1/m
    inner = _track(CAR, (15.0, 2.8), (0.0, 0.0))  # where the left curve goes, 2.8 m aside
    assert leader_row([inner], hist)[0] == 0.0 and leader_row([inner], turn)[0] == 1.0


def test_leader_features_track_the_scene_mirror_with_it_and_feed_the_head():
    from renderworld.world.pose_agents import LEADER_FEATURES, leader_features

    # A car moving ahead in the ego's lane (row 15: y = 0.8 m), the parked one off to the side.
    occ, poses = _scene(mover=(20, 15), mover_step=(1, 0), ego_step=0)
    hist = torch.from_numpy(occ)[None]
    hp = torch.from_numpy(poses)[None].float()
    f = leader_features(hist, hp, GRID)
    m = leader_features(hist.flip(3), hp * torch.tensor([1.0, -1.0, -1.0]), GRID)
    assert f.shape == (1, LEADER_FEATURES) and f.dtype == torch.float32
    assert f[0, 0] == 1.0 and f[0, 2] > 0 and f[0, 4] != 0  # present, moving on, off-centre
    sign = torch.ones(LEADER_FEATURES)
    sign[4] = -1.0  # the lateral offset changes side, nothing else
    torch.testing.assert_close(m[0], f[0] * sign)
    with pytest.raises(ValueError, match="history/history_poses: expected"):
        leader_features(hist, hp[:, :2], GRID)
    cfg = WorldModelConfig(
        codebook_sizes=(8,), token_grid=(4, 4), embed_dim=16, num_heads=2, num_scales=1,
        layers_per_scale=(1,), history_frames=5, future_frames=2,
    )  # fmt: skip
    torch.manual_seed(0)
    model = PoseWarpWorldModel(cfg, agents=1, leader=True)
    assert model.pose.road_user_features == AGENT_FEATURES + LEADER_FEATURES
    with torch.no_grad():
        model.pose.mlp[-1].weight.normal_()
    a, _ = model.predict_poses(hp, torch.tensor([0]), hist[:, -1], hist, GRID)
    assert a.shape == (1, 2, 3) and torch.isfinite(a).all()
    with pytest.raises(ValueError, match="history: the pose head reads agents=1, leader=True"):
        model.predict_poses(hp, torch.tensor([0]), hist[:, -1])
    with pytest.raises(ValueError, match="leader: expected true or false"):
        PoseHead(history=5, steps=2, leader=1)
