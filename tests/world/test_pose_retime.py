"""The plan retimed along its own path: the leader changes how far the ego gets, not where."""

from __future__ import annotations

import math

import pytest
import torch

from renderworld.world.pose_retime import LeaderRetiming, retime_along_path


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
