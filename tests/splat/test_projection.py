"""EWA projection: rotations, means, 2D covariance against a numerical Jacobian, culling."""

import numpy as np
import pytest
import torch
import transforms3d
from hypothesis import given, settings
from hypothesis import strategies as st

from renderworld.geometry import project_points
from renderworld.splat import ALPHA_MIN, EPS2D, project_gaussians, quat_to_rotmat
from renderworld.splat.projection import covariance_3d
from tests.splat.scenes import HEIGHT, WIDTH, look_at_cameras, random_scene


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-2, 2), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_quat_to_rotmat_matches_transforms3d_for_any_norm(q):
    rot = quat_to_rotmat(torch.tensor(q, dtype=torch.float64))
    expected = transforms3d.quaternions.quat2mat(np.asarray(q) / np.linalg.norm(q))
    np.testing.assert_allclose(rot.numpy(), expected, atol=1e-12)


def test_zero_quaternion_is_identity_with_finite_gradient():
    q = torch.zeros(2, 4, dtype=torch.float64, requires_grad=True)
    rot = quat_to_rotmat(q)
    torch.testing.assert_close(rot, torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    (rot * torch.randn(2, 3, 3, dtype=torch.float64)).sum().backward()
    assert torch.isfinite(q.grad).all()


def test_covariance_3d_is_rotated_diagonal():
    quats = torch.tensor([[np.cos(0.25), 0, 0, np.sin(0.25)]], dtype=torch.float64)  # 30° about z
    scales = torch.tensor([[2.0, 1.0, 0.5]], dtype=torch.float64)
    cov = covariance_3d(quats, scales)[0]
    rot = torch.tensor(transforms3d.euler.euler2mat(0, 0, 0.5), dtype=torch.float64)
    torch.testing.assert_close(cov, rot @ torch.diag(scales[0] ** 2) @ rot.T)


def _project(params, **kw):
    viewmats, Ks = look_at_cameras(2)
    args = dict(width=WIDTH, height=HEIGHT, near=0.01, far=100.0)
    args.update(kw)
    return project_gaussians(*params[:4], viewmats, Ks, **args), viewmats, Ks


def test_means_and_depths_match_geometry_project_points():
    params = random_scene(50, seed=2)
    proj, viewmats, Ks = _project(params)
    assert len(proj) > 20
    for row in range(len(proj)):
        c, n = proj.cam_ids[row], proj.gauss_ids[row]
        p_cam = viewmats[c, :3, :3] @ params[0][n] + viewmats[c, :3, 3]
        uv, depth, _ = project_points(p_cam[None], Ks[c])
        torch.testing.assert_close(proj.means2d[row], uv[0])
        torch.testing.assert_close(proj.depths[row], depth[0])


def test_conic_is_inverse_of_linearised_covariance():
    # Σ' = J Σ_cam Jᵀ + 0.3 I with J the numerical Jacobian of the pixel projection.
    params = random_scene(20, seed=4, spread=1.0)
    proj, viewmats, Ks = _project(params)
    cov3 = covariance_3d(params[1], params[2])
    for row in range(len(proj)):
        c, n = proj.cam_ids[row], proj.gauss_ids[row]
        rot, t = viewmats[c, :3, :3], viewmats[c, :3, 3]

        def pix(p, c=c, rot=rot, t=t):
            return project_points((rot @ p + t)[None], Ks[c])[0][0]

        jac = torch.autograd.functional.jacobian(pix, params[0][n])  # [2, 3], world → pixels
        cov2 = jac @ cov3[n] @ jac.T + EPS2D * torch.eye(2, dtype=torch.float64)
        a, b, cc = proj.conics[row]
        conic = torch.stack([torch.stack([a, b]), torch.stack([b, cc])])
        torch.testing.assert_close(
            conic @ cov2, torch.eye(2, dtype=torch.float64), atol=1e-8, rtol=0
        )


def test_near_and_far_planes_cull_by_centre_depth():
    dt = torch.float64
    z = torch.tensor([0.5 - 1e-9, 0.5, 0.5 + 1e-9, 0.2, 50.0, 80.0], dtype=dt)
    n = z.numel()
    params = [
        torch.stack([torch.zeros(n, dtype=dt), torch.zeros(n, dtype=dt), z], 1),
        torch.tensor([[1.0, 0, 0, 0]] * n, dtype=dt),
        torch.full((n, 3), 0.05, dtype=dt),
        torch.full((n,), 0.5, dtype=dt),
    ]
    viewmats, Ks = look_at_cameras(1)
    proj = project_gaussians(*params, viewmats, Ks, WIDTH, HEIGHT, near=0.5, far=60.0)
    assert sorted(proj.gauss_ids.tolist()) == [1, 2, 4]


def test_low_opacity_is_culled():
    params = random_scene(10, seed=1, spread=0.3)
    params[3][:5] = ALPHA_MIN * 0.99
    proj, _, _ = _project(params)
    assert not set(proj.gauss_ids.tolist()) & set(range(5))
    assert set(proj.gauss_ids.tolist()) == set(range(5, 10))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000), spread=st.floats(1.0, 40.0), log_scale=st.floats(-3, 1))
def test_culled_pairs_never_reach_alpha_min_inside_the_image(seed, spread, log_scale):
    # Project once into the real image and once into a 9x larger virtual image around it
    # (where nothing near the real image is pre-culled); a pair dropped from the real image
    # must have alpha < 1/255 at every real pixel centre. Only centres within the real image's
    # Jacobian clamp (1.3x FOV) are compared: beyond it the two projections differ on purpose.
    params = random_scene(150, seed=seed, spread=spread)
    params[2] = params[2] * 10**log_scale
    viewmats, Ks = look_at_cameras(2)
    real = project_gaussians(*params[:4], viewmats, Ks, WIDTH, HEIGHT, 0.01, 1e3)
    big_ks = Ks.clone()
    big_ks[:, 0, 2] += 4 * WIDTH
    big_ks[:, 1, 2] += 4 * HEIGHT
    big = project_gaussians(*params[:4], viewmats, big_ks, 9 * WIDTH, 9 * HEIGHT, 0.01, 1e3)
    kept = set(zip(real.cam_ids.tolist(), real.gauss_ids.tolist()))
    us = torch.arange(WIDTH, dtype=torch.float64) + 0.5 + 4 * WIDTH
    vs = torch.arange(HEIGHT, dtype=torch.float64) + 0.5 + 4 * HEIGHT
    gv, gu = torch.meshgrid(vs, us, indexing="ij")
    for row in range(len(big)):
        c, n = big.cam_ids[row].item(), big.gauss_ids[row].item()
        u, v = big.means2d[row, 0] - 4 * WIDTH, big.means2d[row, 1] - 4 * HEIGHT
        in_clamp = -0.15 * WIDTH < u < 1.15 * WIDTH and -0.15 * HEIGHT < v < 1.15 * HEIGHT
        if (c, n) in kept or not in_clamp:
            continue
        dx, dy = gu - big.means2d[row, 0], gv - big.means2d[row, 1]
        a, b, cc = big.conics[row]
        power = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
        alpha = params[3][n] * torch.exp(-power)
        assert alpha.max().item() < ALPHA_MIN, f"pair ({c}, {n}) culled but visible"


def test_jacobian_clamp_bounds_off_screen_footprints():
    # A Gaussian far to the side (x/z = 5, outside 1.3x the FOV) at a grazing angle keeps a
    # finite, bounded footprint instead of blowing up with x/z.
    dt = torch.float64
    params = [
        torch.tensor([[50.0, 0.0, 10.0]], dtype=dt),
        torch.tensor([[1.0, 0, 0, 0]], dtype=dt),
        torch.tensor([[30.0, 30.0, 30.0]], dtype=dt),
        torch.tensor([0.9], dtype=dt),
    ]
    viewmats, Ks = look_at_cameras(1)
    proj = project_gaussians(*params, viewmats, Ks, WIDTH, HEIGHT, 0.01, 1e3)
    assert len(proj) == 1
    assert torch.isfinite(proj.conics).all() and torch.isfinite(proj.extents).all()
    a, b, c = proj.conics[0]
    var_u = (c / (a * c - b * b)).item()  # Σ'_uu from the inverse
    lim = (WIDTH - 20.0) / 32.0 + 0.3 * (0.5 * WIDTH / 32.0)  # 1.3x FOV on the right side
    clamped = (32.0 * 30.0 / 10.0) ** 2 * (1 + lim**2) + 0.3
    assert var_u == pytest.approx(clamped, rel=1e-9)
    assert var_u < (32.0 * 30.0 / 10.0) ** 2 * (1 + 5.0**2)  # the unclamped value


@pytest.mark.parametrize("scale", [1e-6, 1e3])
def test_extreme_scales_give_finite_positive_definite_conics(scale):
    params = random_scene(30, seed=9)
    params[2] = torch.full_like(params[2], scale)
    proj, _, _ = _project(params)
    a, b, c = proj.conics.unbind(-1)
    assert torch.isfinite(proj.conics).all()
    assert (a > 0).all() and (c > 0).all() and (a * c - b * b > 0).all()
