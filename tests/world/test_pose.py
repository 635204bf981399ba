"""Pose-aware forecasting pieces: pose algebra, history alignment, BEV, pose head, loss."""

from __future__ import annotations

import math

import pytest
import torch

from renderworld.constants import COMMANDS, FREE_ID, GridSpec
from renderworld.world import WorldModelConfig, constant_turn_rate_poses
from renderworld.world.pose import (
    BEV_GROUPS,
    PoseHead,
    PoseWarpWorldModel,
    align_history,
    bev_channels,
    invert_poses,
    kinematic_features,
    motion_channels,
    pose_loss,
)
from renderworld.world.pose_inputs import jittered_history, steady_history

GRID = GridSpec("test", (-4.0, -4.0, 0.0), (4.0, 4.0, 2.0), (8, 8, 2))


def test_invert_poses_round_trip_and_by_hand():
    p = torch.tensor([[2.0, 0.0, math.pi / 2]])
    # Frame B sits 2 m ahead of A, turned left 90 deg: A's origin, (-2, 0) from B in A's axes,
    # is R(-90) (-2, 0) = (0, 2) in B's axes (on B's left), and A's heading is -90 deg there.
    torch.testing.assert_close(invert_poses(p), torch.tensor([[0.0, 2.0, -math.pi / 2]]))
    q = torch.tensor([[1.5, -0.7, 0.3], [-2.0, 4.0, -2.5]], dtype=torch.float64)
    torch.testing.assert_close(invert_poses(invert_poses(q)), q)
    with pytest.raises(ValueError, match=r"poses: expected \[\.\.\., 3\]"):
        invert_poses(torch.zeros(2, 2))


def test_align_history_rotates_a_past_frame_into_the_current_one():
    occ = torch.full((1, 2, *GRID.shape), FREE_ID, dtype=torch.uint8)
    occ[0, 0, 6, 4, 0] = 4  # frame t-1: a car 2.5 m ahead (centre (2.5, 0.5))
    occ[0, 1, 1, 1, 1] = 15  # the current frame: left alone
    poses = torch.tensor([[[0.0, 0.0, math.pi / 2], [0.0, 0.0, 0.0]]])  # t-1 faced left of now
    out = align_history(occ, poses, GRID)
    # In the current frame the car is at R(90) (2.5, 0.5) = (-0.5, 2.5): voxel (3, 6).
    assert out[0, 0, 3, 6, 0] == 4 and (out[0, 0] == 4).sum() == 1
    assert torch.equal(out[0, 1], occ[0, 1])
    with pytest.raises(ValueError, match="occupancy/history_poses: expected"):
        align_history(occ, poses[:, :1], GRID)


def test_bev_channels_collapse_z_by_group():
    occ = torch.full((1, *GRID.shape), FREE_ID, dtype=torch.uint8)
    occ[0, 2, 3, 1] = 11  # road
    occ[0, 5, 5, 0] = 4  # car -> objects channel
    bev = bev_channels(occ)
    assert bev.shape == (1, len(BEV_GROUPS), 8, 8)
    assert bev[0, 0, 2, 3] == 1 and bev[0, 0].sum() == 1
    assert bev[0, -1, 5, 5] == 1 and bev[0, -1].sum() == 1 and bev[0, 1:-1].sum() == 0
    with pytest.raises(ValueError, match=r"occupancy: expected a \[B, X, Y, Z\] tensor"):
        bev_channels(occ[0])


def _history(b=2, h=3):
    hist = torch.zeros(b, h, 3)
    hist[:, :, 0] = torch.arange(-(h - 1), 1, dtype=torch.float32) * 4.0  # 4 m per step
    hist[1, :, 2] = torch.tensor([-0.2, -0.1, 0.0])  # turning left
    return hist


def test_pose_head_starts_at_constant_turn_rate_and_the_command_selects_a_mode():
    head = PoseHead(history=3, steps=4)
    hist, cmd = _history(), torch.tensor([0, 2])
    bev = torch.zeros(2, len(BEV_GROUPS), 8, 8)
    poses, modes = head(hist, cmd, bev)
    assert poses.shape == (2, 4, 3) and modes.shape == (2, len(COMMANDS), 4, 3)
    torch.testing.assert_close(poses, constant_turn_rate_poses(hist.double(), 4).float())
    with torch.no_grad():
        head.mlp[-1].bias.copy_(torch.arange(len(COMMANDS) * 4 * 3, dtype=torch.float32))
    poses, modes = head(hist, cmd, bev)
    for i, c in enumerate(cmd.tolist()):
        torch.testing.assert_close(poses[i], modes[i, c])
    assert not torch.allclose(modes[:, 0], modes[:, 1])
    with pytest.raises(ValueError, match=r"history_poses: expected \[B, 3, 3\]"):
        head(hist[:, :2], cmd, bev)
    with pytest.raises(ValueError, match="command: expected int64"):
        head(hist, cmd.float(), bev)


def test_pose_loss_by_hand():
    gt = torch.zeros(1, 2, 3)
    pred = torch.tensor([[[3.0, 4.0, 0.1], [0.0, 0.0, 2 * math.pi - 0.2]]])
    out = pose_loss(pred, gt, yaw_weight=5.0)
    assert out["pose_l2"].item() == pytest.approx(2.5, abs=1e-5)  # (5 + 0) / 2
    assert out["pose_yaw"].item() == pytest.approx(0.15, abs=1e-5)  # wrapped: (0.1 + 0.2) / 2
    assert out["pose"].item() == pytest.approx(2.5 + 0.75, abs=1e-5)
    masked = pose_loss(pred, gt, torch.tensor([[True, False]]))
    assert masked["pose_l2"].item() == pytest.approx(5.0, abs=1e-5)
    with pytest.raises(ValueError, match="pred/gt: expected equal"):
        pose_loss(pred, gt[:, :1])


def test_pose_warp_model_scores_the_future_frames_with_a_bonus_on_the_warped_code():
    cfg = WorldModelConfig(codebook_sizes=(16,), token_grid=(4, 4), embed_dim=16, num_heads=2,
                           num_scales=1, layers_per_scale=(1,), history_frames=3,
                           future_frames=2)  # fmt: skip
    model = PoseWarpWorldModel(cfg, copy_bonus=0.0).eval()
    tokens = torch.randint(0, 16, (2, 4, 1, 4, 4))  # 2 aligned history + 2 warped frames
    poses = torch.zeros(2, 4, 3)
    cmd = torch.tensor([1, 2])
    base = model(tokens, poses, cmd)
    assert len(base) == 1 and base[0].shape == (2, 2, 16, 4, 4)
    with torch.no_grad():
        model.copy_bonus.fill_(3.0)
    bumped = model(tokens, poses, cmd)[0]
    diff = bumped - base[0]  # +3 exactly at each warped frame's own code
    onehot = torch.nn.functional.one_hot(tokens[:, 2:, 0], 16).permute(0, 1, 4, 2, 3).float()
    torch.testing.assert_close(diff, 3.0 * onehot)
    occ = torch.full((2, *GRID.shape), FREE_ID, dtype=torch.uint8)
    p, _ = model.predict_poses(_history(), cmd, occ)
    assert p.shape == (2, 2, 3) and torch.isfinite(p).all()


def test_pose_loss_step_weights():
    gt = torch.zeros(1, 2, 3)
    pred = torch.tensor([[[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]])
    assert pose_loss(pred, gt)["pose_l2"].item() == pytest.approx(2.0, abs=1e-5)
    near = pose_loss(pred, gt, step_weights=torch.tensor([3.0, 1.0]))
    assert near["pose_l2"].item() == pytest.approx((3 * 1 + 1 * 3) / 4, abs=1e-5)
    with pytest.raises(ValueError, match=r"step_weights: expected \[2\]"):
        pose_loss(pred, gt, step_weights=torch.ones(3))


def test_pose_head_ctr_cv_anchors_blend_and_saturate():
    head = PoseHead(history=3, steps=4, anchors="ctr_cv")
    hist, cmd = _history(), torch.tensor([2, 2])
    bev = torch.zeros(2, len(BEV_GROUPS), 8, 8)
    ctr = constant_turn_rate_poses(hist.double(), 4).float()
    still = hist.clone()
    still[:, :, 2] = 0
    cv = constant_turn_rate_poses(still.double(), 4).float()
    poses, _ = head(hist, cmd, bev)
    torch.testing.assert_close(poses, 0.5 * ctr + 0.5 * cv)  # half each at initialisation
    with torch.no_grad():  # the CTR logit of every mode and step far negative: pure CV
        head.mlp[-1].bias.view(len(COMMANDS), 4, 4)[..., 3] = -50.0
    poses, _ = head(hist, cmd, bev)
    torch.testing.assert_close(poses, cv)
    assert cv[1, :, 2].abs().max() == 0 and ctr[1, :, 2].abs().max() > 0  # they differ
    with pytest.raises(ValueError, match="anchors: expected one of"):
        PoseHead(history=3, steps=4, anchors="cv")


def test_kinematic_features_resolve_small_changes_and_mirror():
    h = 5
    hist = torch.zeros(3, h, 3)
    hist[:, :, 0] = torch.arange(-(h - 1), 1, dtype=torch.float32) * 3.0  # 3 m per step
    hist[1, -1, 2] = math.radians(0.3)  # a turn starting: 0.3 deg in the last step
    hist[2, :, 0] = torch.tensor([-10.5, -7.5, -4.75, -2.25, 0.0])  # braking: 3, 2.75, 2.5, 2.25
    f = kinematic_features(hist)
    assert f.shape == (3, 4 * h - 6) and torch.isfinite(f).all()
    n = h - 1
    steps, dsteps = f[:, :n], f[:, n : 2 * n - 1]
    dyaw, ddyaw = f[:, 2 * n - 1 : 3 * n - 1], f[:, 3 * n - 1 :]
    torch.testing.assert_close(steps[0], torch.full((n,), math.asinh(3.0) / 3))
    assert dsteps[0].abs().max() == 0 and dyaw[0].abs().max() == 0  # steady, straight
    # 0.3 deg is far from zero on this scale (asinh(3) / 3 = 0.6), unlike in radians (0.005).
    assert dyaw[1, -1].item() == pytest.approx(math.asinh(3.0) / 3, rel=1e-4)
    assert ddyaw[1, -1].item() > 0.5 and dyaw[1, :-1].abs().max() < 1e-6
    # A 0.25 m per step speed drop (0.5 m/s per 0.5 s) is as clear, with its sign.
    assert (dsteps[2] < -1.0).all()
    # Mirroring the scene (y -> -y, yaw -> -yaw) flips the heading features only.
    mirrored = hist.clone()
    mirrored[..., 1:] = -mirrored[..., 1:]
    g = kinematic_features(mirrored)
    torch.testing.assert_close(g[:, : 2 * n - 1], f[:, : 2 * n - 1])
    torch.testing.assert_close(g[:, 2 * n - 1 :], -f[:, 2 * n - 1 :])
    # A heading change across +-180 deg is the short way round, not 360 deg.
    wrap = torch.zeros(1, 2, 3)
    wrap[0, 0, 2], wrap[0, 1, 2] = math.radians(179.0), math.radians(-179.0)
    wrap[0, 1, 0] = 1.0
    assert kinematic_features(wrap)[0, 1].item() == pytest.approx(math.asinh(20.0) / 3, rel=1e-4)


def test_steady_history_keeps_the_last_step_and_drops_the_trend():
    h = 5
    hist = torch.zeros(2, h, 3, dtype=torch.float64)
    hist[0, :, 0] = torch.tensor([-10.5, -7.5, -4.75, -2.25, 0.0])  # braking: 3 ... 2.25 m/step
    # A steady left turn: each step 2 m along a heading 0.1 rad less than the next one's.
    w, yaw, pts = 0.1, 0.0, [torch.zeros(2, dtype=torch.float64)]
    for _ in range(h - 1):
        yaw -= w
        pts.append(pts[-1] - 2.0 * torch.tensor([math.cos(yaw + w), math.sin(yaw + w)]))
    hist[1, :, :2] = torch.stack(pts[::-1])
    hist[1, :, 2] = -w * torch.arange(h - 1, -1, -1, dtype=torch.float64)
    out = steady_history(hist)
    # The turn at constant rate and speed is steady already: it comes back unchanged.
    torch.testing.assert_close(out[1], hist[1])
    # The braking one keeps its current pose and last step (2.25 m), every earlier step the same.
    torch.testing.assert_close(out[0, -2:], hist[0, -2:])
    torch.testing.assert_close(out[0, :, 0], torch.tensor([-9.0, -6.75, -4.5, -2.25, 0.0]).double())
    f = kinematic_features(out.float())
    n = h - 1
    assert f[0, n : 2 * n - 1].abs().max() == 0  # no speed change left
    assert f[:, 3 * n - 1 :].abs().max() < 1e-4  # nor a change of turn rate
    with pytest.raises(ValueError, match=r"history_poses: expected \[B, H>=2, 3\]"):
        steady_history(torch.zeros(1, 1, 3))


def test_jittered_history_moves_past_positions_only_by_the_noise_asked():
    torch.manual_seed(0)
    hist = torch.zeros(4000, 5, 3)
    hist[:, :, 0] = torch.tensor([-12.0, -9.0, -6.0, -3.0, 0.0])
    hist[:, :, 2] = torch.tensor([-0.04, -0.03, -0.02, -0.01, 0.0])
    out = jittered_history(hist, 0.03)
    assert out.shape == hist.shape and out.dtype == hist.dtype
    torch.testing.assert_close(out[:, -1], hist[:, -1])  # the current pose is the origin still
    torch.testing.assert_close(out[..., 2], hist[..., 2])  # headings stay
    moved = out[:, :-1, :2] - hist[:, :-1, :2]
    assert moved.std().item() == pytest.approx(0.03, rel=0.05)
    assert moved.mean().abs().item() < 0.002
    # A 3 cm trend per step reads as a speed change the head can resolve; the noise hides it.
    f = kinematic_features(hist)[:, 4:7]
    assert f.abs().max() < 1e-4 and kinematic_features(out)[:, 4:7].abs().mean() > 0.5
    assert jittered_history(hist, 0.0) is hist
    with pytest.raises(ValueError, match="sigma_m: expected a number >= 0"):
        jittered_history(hist, -0.1)
    with pytest.raises(ValueError, match=r"history_poses: expected \[B, H, 3\]"):
        jittered_history(torch.zeros(5, 3), 0.03)


def test_pose_head_with_kinematics_starts_at_its_anchor_and_reads_them():
    head = PoseHead(history=3, steps=4, kinematics=True)
    hist, cmd = _history(), torch.tensor([0, 2])
    bev = torch.zeros(2, len(BEV_GROUPS), 8, 8)
    poses, _ = head(hist, cmd, bev)
    torch.testing.assert_close(poses, constant_turn_rate_poses(hist.double(), 4).float())
    assert head.mlp[0].in_features == PoseHead(3, 4).mlp[0].in_features + (4 * 3 - 6)
    with torch.no_grad():
        head.mlp[-1].weight.normal_()
    braking = hist.clone()
    braking[:, 0, 0] = -8.5  # the same current frame, the first step 0.5 m longer
    changed = head(braking, cmd, bev)[0] - head(hist, cmd, bev)[0]
    assert changed.abs().max() > 0


def test_motion_channels_put_past_objects_where_they_were_in_the_current_frame():
    occ = torch.full((1, 3, *GRID.shape), FREE_ID, dtype=torch.uint8)
    occ[0, 0, 4, 4, 0] = 4  # t-2: a car at (0.5, 0.5) of its frame
    occ[0, 1, 4, 4, 1] = 9  # t-1: a pedestrian at (0.5, 0.5) of its frame
    occ[0, 1, 5, 5, 0] = 11  # and road: not an object
    occ[0, 2, 7, 7, 0] = 4  # the current frame's objects are not in the motion channels
    poses = torch.zeros(1, 3, 3)
    poses[0, 0, 0], poses[0, 1, 0] = -2.0, -1.0  # the ego drove 1 m per step along x
    m = motion_channels(occ, poses, GRID, frames=2)
    assert m.shape == (1, 2, 8, 8) and m.dtype == torch.float32
    # t-1 first: the pedestrian 1 m behind where it is in its own frame, the car 2 m behind.
    assert m[0, 0, 3, 4] == 1 and m[0, 0].sum() == 1
    assert m[0, 1, 2, 4] == 1 and m[0, 1].sum() == 1
    torch.testing.assert_close(motion_channels(occ, poses, GRID, frames=1), m[:, :1])
    with pytest.raises(ValueError, match=r"frames: expected 1\.\.2"):
        motion_channels(occ, poses, GRID, frames=3)
    with pytest.raises(ValueError, match="history/history_poses: expected"):
        motion_channels(occ, poses[:, :2], GRID, frames=1)


def test_pose_head_with_motion_reads_where_the_others_were():
    cfg = WorldModelConfig(
        codebook_sizes=(8,), token_grid=(4, 4), embed_dim=16, num_heads=2, num_scales=1,
        layers_per_scale=(1,), history_frames=3, future_frames=2,
    )  # fmt: skip
    torch.manual_seed(0)
    model = PoseWarpWorldModel(cfg, motion_frames=2)
    assert model.pose.bev[0].in_channels == len(BEV_GROUPS) + 2
    with torch.no_grad():
        model.pose.mlp[-1].weight.normal_()
    hist, cmd = torch.zeros(1, 3, 3), torch.tensor([0])  # the ego stands: nothing leaves the grid
    occ = torch.full((1, 3, *GRID.shape), FREE_ID, dtype=torch.uint8)
    occ[0, :, 6, 4, 0] = 4  # a car that stood still
    still, _ = model.predict_poses(hist, cmd, occ[:, -1], occ, GRID)
    moved = occ.clone()
    moved[0, 0, 6, 4, 0], moved[0, 0, 2, 4, 0] = FREE_ID, 4  # it was further back at t-2
    # The same current frame, another past: another plan.
    assert not torch.equal(model.predict_poses(hist, cmd, moved[:, -1], moved, GRID)[0], still)
    with pytest.raises(ValueError, match="history: the pose head reads motion_frames=2"):
        model.predict_poses(hist, cmd, occ[:, -1])
    with pytest.raises(ValueError, match=r"motion_frames: expected 0\.\.2"):
        PoseHead(history=3, steps=2, motion_frames=3)


def test_pose_warp_model_computes_only_the_scored_positions_as_the_reference_does():
    """The model's logits (the net's up-path and heads run on the scored positions only) equal
    the reference: every position computed, the bonus added, the history's positions dropped."""
    cfg = WorldModelConfig(codebook_sizes=(16, 8), token_grid=(4, 4), embed_dim=16, num_heads=2,
                           num_scales=2, layers_per_scale=(1, 1), history_frames=3,
                           future_frames=3)  # fmt: skip
    torch.manual_seed(0)
    model = PoseWarpWorldModel(cfg, copy_bonus=2.0).eval()
    tokens = torch.stack([torch.randint(0, k, (2, 5, 4, 4)) for k in (16, 8)], 2)
    poses = torch.randn(2, 5, 3)
    cmd = torch.tensor([0, 2])
    got = model(tokens, poses, cmd)
    with torch.no_grad():
        out = model.net(tokens, torch.diff(poses[..., :2], dim=1), cmd)
    for g, (lg, mine) in enumerate(zip(out.logits, got)):
        bonus = model.copy_bonus[g].expand_as(tokens[:, :, g, None])
        ref = lg.scatter_add(2, tokens[:, :, g, None], bonus)[:, 2:]
        assert mine.shape == ref.shape == (2, 3, cfg.codebook_sizes[g], 4, 4)
        torch.testing.assert_close(mine, ref, rtol=1e-5, atol=1e-6)


def test_pose_head_with_a_finer_readout_tells_where_a_feature_lies():
    hist, cmd = torch.zeros(1, 3, 3), torch.tensor([0])
    near = torch.zeros(1, len(BEV_GROUPS), 48, 48)
    near[0, 0, 18:22, 22:26] = 1.0  # a patch ahead of the ego ...
    far = torch.roll(near, 8, dims=2)  # ... and the same patch 8 cells (one readout cell) on
    outputs = {}
    for pool in (1, 6):
        torch.manual_seed(0)
        head = PoseHead(history=3, steps=2, bev_pool=pool)
        assert head.bev[-2].in_features == 32 * pool**2
        with torch.no_grad():
            head.mlp[-1].weight.normal_()
        outputs[pool] = head(hist, cmd, near)[0], head(hist, cmd, far)[0]
    # Pooled to one cell, where the patch lies is lost; read out in 6 x 6 cells, it is not.
    torch.testing.assert_close(*outputs[1])
    assert not torch.allclose(*outputs[6])
    with pytest.raises(ValueError, match="bev_pool: expected an int >= 1"):
        PoseHead(history=3, steps=2, bev_pool=0)
