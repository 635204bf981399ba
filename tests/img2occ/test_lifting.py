"""Lifting: voxels get the features of the cameras that see them, zeros when none does."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.img2occ import lift_features

H, W, D = 6, 10, 4
F_PX = 8.0


def _forward_camera(yaw_deg: float) -> np.ndarray:
    """cam_to_ego of a camera at (0, 0, 1.5) looking along ego heading ``yaw`` (deg)."""
    yaw = np.deg2rad(yaw_deg)
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, fwd], axis=1)  # columns: camera x, y, z in ego
    pose[:3, 3] = [0.0, 0.0, 1.5]
    return pose


def _k() -> np.ndarray:
    return np.array([[F_PX, 0, W / 2], [0, F_PX, H / 2], [0, 0, 1]], dtype=np.float64)


def _point_at_pixel(pose, i, j, depth):
    """Ego point whose projection is the centre of feature pixel (column i, row j)."""
    k = _k()
    x = (i + 0.5 - k[0, 2]) * depth / k[0, 0]
    y = (j + 0.5 - k[1, 2]) * depth / k[1, 1]
    return (pose @ np.array([x, y, depth, 1.0]))[:3]


def _inputs(poses):
    c = len(poses)
    feats = torch.arange(c * D * H * W, dtype=torch.float64).view(1, c, D, H, W)
    cam = torch.tensor(np.stack(poses))[None]
    ks = torch.tensor(np.stack([_k()] * c))[None]
    return feats, cam, ks


def test_seen_voxel_gets_that_cameras_feature_and_behind_gets_zero():
    front = _forward_camera(0.0)
    feats, cam, ks = _inputs([front])
    seen = _point_at_pixel(front, 3, 2, depth=12.0)
    behind = np.array([-10.0, 0.3, 1.0])
    centres = torch.tensor(np.stack([seen, behind]))
    out = lift_features(feats, cam, ks, centres)
    torch.testing.assert_close(out.features[0, :, 0], feats[0, 0, :, 2, 3])
    torch.testing.assert_close(out.features[0, :, 1], torch.zeros(D, dtype=torch.float64))
    assert out.count[0].tolist() == [1.0, 0.0]
    assert out.depth[0, 0].item() == pytest.approx(12.0)
    assert out.depth[0, 1].item() == 0.0
    np.testing.assert_allclose(out.view_dir[0, 0].numpy(), (seen - front[:3, 3]) / 12.0 * 1.0,
                               atol=0.05)  # fmt: skip
    assert out.view_dir[0, 1].abs().sum().item() == 0.0


def test_average_over_cameras_that_see_the_voxel_only():
    front, left, back = _forward_camera(0.0), _forward_camera(30.0), _forward_camera(180.0)
    feats, cam, ks = _inputs([front, left, back])
    # A point on the front camera's pixel (4, 3) at 10 m; find where the left camera sees it.
    p = _point_at_pixel(front, 4, 3, depth=10.0)
    out = lift_features(feats, cam, ks, torch.tensor(p[None]))
    assert out.count[0, 0].item() == 2.0  # the back camera does not see it
    # Reference: bilinear sample of each seeing camera at its projection (pixel-area coords).
    want = []
    for ci, pose in enumerate([front, left]):
        pc = np.linalg.inv(pose) @ np.append(p, 1.0)
        u, v = _k()[0, 0] * pc[0] / pc[2] + W / 2, _k()[1, 1] * pc[1] / pc[2] + H / 2
        x, y = np.clip(u - 0.5, 0, W - 1), np.clip(v - 0.5, 0, H - 1)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
        ax, ay = x - x0, y - y0
        f = feats[0, ci].numpy()
        want.append(
            f[:, y0, x0] * (1 - ax) * (1 - ay) + f[:, y0, x1] * ax * (1 - ay)
            + f[:, y1, x0] * (1 - ax) * ay + f[:, y1, x1] * ax * ay
        )  # fmt: skip
    np.testing.assert_allclose(out.features[0, :, 0].numpy(), np.mean(want, 0), rtol=1e-9)


def test_outside_the_image_is_not_seen():
    front = _forward_camera(0.0)
    feats, cam, ks = _inputs([front])
    far_left = np.array([5.0, 40.0, 1.5])  # in front (z > 0) but far outside the field of view
    out = lift_features(feats, cam, ks, torch.tensor(far_left[None]))
    assert out.count.item() == 0.0
    assert out.features.abs().sum().item() == 0.0


def test_gradients_flow_to_features():
    front = _forward_camera(0.0)
    feats, cam, ks = _inputs([front])
    feats = feats.clone().requires_grad_(True)
    p = _point_at_pixel(front, 5, 1, depth=7.0)
    out = lift_features(feats, cam, ks, torch.tensor(p[None]))
    out.features.sum().backward()
    assert feats.grad[0, 0, :, 1, 5].tolist() == [1.0] * D
    assert feats.grad.sum().item() == pytest.approx(D)


def test_lift_validates_shapes():
    feats, cam, ks = _inputs([_forward_camera(0.0)])
    with pytest.raises(ValueError, match="cam_to_ego"):
        lift_features(feats, cam[:, :, :3], ks, torch.zeros(2, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="centres"):
        lift_features(feats, cam, ks, torch.zeros(2, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match="features"):
        lift_features(feats[0], cam, ks, torch.zeros(2, 3, dtype=torch.float64))


@pytest.mark.parametrize("depth_aware", [False, True])
def test_sampling_only_the_seen_voxels_equals_the_dense_reference(depth_aware):
    """The default (each camera sampled at the voxels it sees) gives the dense twin's values and
    gradients: a batch of 2 whose cameras see different voxels, one camera seeing none."""
    g = torch.Generator().manual_seed(0)
    poses = [_forward_camera(0.0), _forward_camera(120.0), _forward_camera(240.0)]
    away = _forward_camera(0.0)
    away[:3, 3] = [500.0, 0.0, 1.5]  # far ahead, looking further ahead: sees no voxel
    cams = torch.tensor(np.stack([np.stack(poses), np.stack([poses[0], poses[1], away])]))
    ks = torch.tensor(np.stack([_k()] * 3))[None].expand(2, 3, 3, 3)
    centres = torch.rand(400, 3, generator=g, dtype=torch.float64) * 40 - 20
    feats = torch.randn(2, 3, D, H, W, generator=g, dtype=torch.float64)
    extra = {}
    if depth_aware:
        edges = torch.linspace(0.0, 30.0, 7, dtype=torch.float64)
        cdf = torch.rand(2, 3, 7, H, W, generator=g, dtype=torch.float64).cumsum(2) / 7
        probs = torch.rand(2, 3, 5, 2 * H, 2 * W, generator=g, dtype=torch.float64)
        extra = {"depth_cdf": cdf, "class_probs": probs, "edges": edges, "radius": 0.8}
    outs, grads = [], []
    for sparse in (True, False):
        x = feats.clone().requires_grad_(True)
        ins = {k: (v.clone().requires_grad_(True) if k in ("depth_cdf", "class_probs") else v)
               for k, v in extra.items()}  # fmt: skip
        out = lift_features(x, cams, ks, centres, sparse=sparse, **ins)
        loss = (out.features**2).sum() + (out.extras.sum() if depth_aware else 0.0)
        loss.backward()
        outs.append(out)
        grads.append([x.grad, *(ins[k].grad for k in ("depth_cdf", "class_probs") if k in ins)])
    assert 0 < (outs[0].count > 0).float().mean() < 1  # some voxels seen, some not
    assert outs[0].count[1].max() <= 2  # the second sample's third camera sees nothing
    for name in ("features", "count", "depth", "view_dir", "extras"):
        a, b = getattr(outs[0], name), getattr(outs[1], name)
        if a is None:
            assert b is None
            continue
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    for a, b in zip(grads[0], grads[1], strict=True):
        assert a.abs().sum() > 0
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
