"""Hard cases of docs/conventions.md#numerics.

Outputs and gradients finite, fast backends match the reference.
"""

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.splat.scenes import ALL_IMPLS, FAST_IMPLS, HEIGHT, WIDTH, grads, random_scene


def _finite(out, g):
    for t in list(out) + list(g):
        assert torch.isfinite(t).all()


def _close(out, ref_out, atol):
    for a, b in zip(out, ref_out):
        assert (a - b).abs().max().item() <= atol


def _check_all(params, atol=1e-5, dtypes=(torch.float64, torch.float32), **kw):
    """Every backend: finite outputs and gradients; fast ones match the reference in float64."""
    for dtype in dtypes:
        ps = [p.to(dtype) for p in params]
        ref_out, ref_g = grads(ps, "reference", **kw)
        _finite(ref_out, ref_g)
        for impl in FAST_IMPLS:
            out, g = grads(ps, impl, **kw)
            _finite(out, g)
            if dtype == torch.float64:
                _close(out, ref_out, atol)


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    log_scales=st.lists(st.floats(-6, 3), min_size=3, max_size=3),
    seed=st.integers(0, 1000),
)
def test_extreme_scales_from_1e_minus_6_to_1e3(log_scales, seed):
    params = random_scene(25, seed=seed)
    params[2] = params[2] * 0 + torch.tensor([10.0**s for s in log_scales], dtype=torch.float64)
    _check_all(params)


@pytest.mark.parametrize("scale", [1e-6, 1e3])
def test_uniform_extreme_scale(scale):
    params = random_scene(25, seed=1)
    params[2] = torch.full_like(params[2], scale)
    _check_all(params)


@pytest.mark.parametrize("qnorm", [0.0, 1e-30, 1e-12, 1e-6])
def test_zero_and_near_zero_quaternions(qnorm):
    params = random_scene(25, seed=2)
    q = params[1]
    params[1] = q / q.norm(dim=1, keepdim=True) * qnorm
    _check_all(params)


@pytest.mark.parametrize("offset", [-1e-3, -1e-9, 0.0, 1e-9, 1e-3])
def test_gaussians_on_and_around_the_near_plane(offset):
    near = 0.5
    params = random_scene(20, seed=3, spread=0.05)
    params[0][:10, 2] = near + offset  # half of them at the plane, the rest behind it
    params[0][10:, 2] = 3.0
    _check_all(params, near=near)


def test_grazing_angle_flat_gaussians():
    # Disc-like Gaussians seen edge-on: the projected covariance is rank one before the low-pass.
    n = 12
    params = random_scene(n, seed=4, spread=1.0)
    params[2] = torch.tensor([[1.0, 1e-6, 1.0]], dtype=torch.float64).repeat(n, 1)
    params[1] = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(n, 1)
    _check_all(params)


@pytest.mark.parametrize("u", [-3.0, -0.5, 0.0, 0.5, float(WIDTH), WIDTH + 2.0])
def test_gaussians_at_the_image_border(u):
    params = random_scene(6, seed=5)
    z = 8.0
    params[0][:, 2] = z
    params[0][:, 0] = (u - 20.0) * z / 32.0  # centre column u for camera 0 (fx 32, cx 20)
    params[0][:, 1] = torch.linspace(-15.0, 15.0, 6, dtype=torch.float64) * z / 30.0
    params[2] = torch.full_like(params[2], 0.05)
    _check_all(params)


def test_thousands_stacked_on_one_pixel_saturate():
    n = 1500
    params = random_scene(n, dim=17, seed=6, spread=1e-3)
    params[3] = torch.full_like(params[3], 0.9)
    _check_all(params, dtypes=(torch.float64,))
    out, _ = grads(params, FAST_IMPLS[-1])
    centre = out.alpha[0, HEIGHT // 2, WIDTH // 2].item()
    assert 1 - 1e-3 < centre < 1.0  # saturated: transmittance stopped just above 1e-4


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_constant_features_render_as_constant_times_alpha(impl):
    params = random_scene(60, dim=5, seed=8)
    params[4] = torch.full_like(params[4], 3.25)
    out, g = grads(params, impl)
    torch.testing.assert_close(out.features, 3.25 * out.alpha[..., None].expand_as(out.features))
    _finite(out, g)


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_large_coordinates_and_far_plane(impl):
    params = random_scene(30, seed=10, depth=5e3, spread=500.0)
    params[2] = params[2] * 100
    out, g = grads(params, impl, far=1e4)
    _finite(out, g)
    out_far, _ = grads(params, impl, far=10.0)
    assert torch.count_nonzero(out_far.alpha) == 0
