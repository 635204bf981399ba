"""Fast backends against the dense reference: forward, backward, gradcheck, hand-computed cases."""

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from renderworld.splat import ALPHA_MAX, rasterize
from tests.splat.scenes import (
    ALL_IMPLS,
    FAST_IMPLS,
    HEIGHT,
    WIDTH,
    grads,
    look_at_cameras,
    random_scene,
    render,
)


def _cosine(a, b):
    a, b = a.flatten(), b.flatten()
    if a.norm() == 0 and b.norm() == 0:
        return 1.0
    return float(torch.nn.functional.cosine_similarity(a, b, dim=0))


def _assert_matches_reference(params, impl, **kw):
    ref_out, ref_grads = grads(params, "reference", **kw)
    out, g = grads(params, impl, **kw)
    for name, a, b in zip(("features", "depth", "alpha"), out, ref_out):
        err = (a - b).abs().max().item()
        assert err <= 1e-5, f"{impl} {name}: max abs error {err}"
    names = ("means", "quats", "scales", "opacities", "features")
    for name, a, b in zip(names, g, ref_grads):
        assert torch.isfinite(a).all(), f"{impl} d/d{name} not finite"
        assert _cosine(a, b) >= 0.999, f"{impl} d/d{name}: cosine {_cosine(a, b)}"
        scale = b.abs().max().item() + 1e-12
        assert (a - b).abs().max().item() <= 1e-6 * max(1.0, scale), f"{impl} d/d{name}"


@pytest.mark.parametrize("impl", FAST_IMPLS)
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_reference_on_random_scene(impl, seed):
    params = random_scene(120, dim=4, seed=seed)
    _assert_matches_reference(params, impl)


@pytest.mark.parametrize("impl", FAST_IMPLS)
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(1, 60),
    dim=st.integers(1, 6),
    seed=st.integers(0, 10_000),
    depth=st.floats(0.5, 30.0),
    spread=st.floats(0.1, 6.0),
)
def test_matches_reference_hypothesis(impl, n, dim, seed, depth, spread):
    params = random_scene(n, dim=dim, seed=seed, depth=depth, spread=spread)
    _assert_matches_reference(params, impl)


@pytest.mark.parametrize("impl", FAST_IMPLS)
def test_matches_reference_with_17_channels_and_dense_overlap(impl):
    # Many Gaussians over few pixels: long per-tile lists, chunk boundaries, early termination.
    params = random_scene(400, dim=17, seed=7, spread=0.8)
    _assert_matches_reference(params, impl)


def _tiny_scene():
    # Three Gaussians, well inside the image, alphas far from the 1/255 and 0.99 kinks at the
    # pixel centres that matter (opacity 0.5 max), transmittance never near 1e-4.
    means = torch.tensor(
        [[0.1, 0.05, 5.0], [-0.2, 0.1, 6.0], [0.15, -0.1, 7.0]], dtype=torch.float64
    )
    quats = torch.tensor(
        [[1.0, 0.1, 0.2, 0.3], [0.9, -0.2, 0.1, 0.0], [0.5, 0.5, -0.1, 0.2]], dtype=torch.float64
    )
    scales = torch.tensor(
        [[0.3, 0.2, 0.25], [0.2, 0.35, 0.3], [0.4, 0.3, 0.2]], dtype=torch.float64
    )
    opacities = torch.tensor([0.5, 0.4, 0.45], dtype=torch.float64)
    features = torch.tensor([[1.0, -0.5], [0.2, 0.7], [-0.3, 0.4]], dtype=torch.float64)
    return [means, quats, scales, opacities, features]


def _gradcheck(impl, fast_mode):
    viewmats, Ks = look_at_cameras(1)
    Ks = Ks.clone()
    Ks[:, :2] /= 4.0  # a 10 x 8 image keeps gradcheck quick
    params = [p.clone().requires_grad_(True) for p in _tiny_scene()]

    def fn(*ps):
        r = rasterize(*ps, viewmats, Ks, 10, 8, backend=impl)
        return r.features, r.depth, r.alpha

    return torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=fast_mode)


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_gradcheck_tiny_scene(impl):
    assert _gradcheck(impl, fast_mode=True)


@pytest.mark.slow
@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_gradcheck_tiny_scene_full_jacobian(impl):
    assert _gradcheck(impl, fast_mode=False)


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_single_gaussian_hand_computed(impl):
    # An isotropic Gaussian 4 m ahead on the optical axis of a camera with f = 40 px:
    # σ_2d² = (f σ / z)² + 0.3 and alpha at a pixel centre is o·exp(-d²/(2 σ_2d²)).
    f, z, sigma, o = 40.0, 4.0, 0.1, 0.6
    dt = torch.float64
    viewmats = torch.eye(4, dtype=dt)[None]
    Ks = torch.tensor([[[f, 0, 10.0], [0, f, 8.0], [0, 0, 1]]], dtype=dt)
    params = [
        torch.tensor([[0.0, 0.0, z]], dtype=dt),
        torch.tensor([[1.0, 0, 0, 0]], dtype=dt),
        torch.full((1, 3), sigma, dtype=dt),
        torch.tensor([o], dtype=dt),
        torch.tensor([[2.0, -1.0]], dtype=dt),
    ]
    r = rasterize(*params, viewmats, Ks, 20, 16, backend=impl)
    var = (f * sigma / z) ** 2 + 0.3
    u = torch.arange(20, dtype=dt) + 0.5 - 10.0
    v = torch.arange(16, dtype=dt) + 0.5 - 8.0
    d2 = v[:, None] ** 2 + u[None, :] ** 2
    alpha = o * torch.exp(-0.5 * d2 / var)
    alpha = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))
    torch.testing.assert_close(r.alpha[0], alpha, atol=1e-12, rtol=0)
    torch.testing.assert_close(r.features[0, ..., 0], 2.0 * alpha, atol=1e-12, rtol=0)
    expected_depth = torch.where(alpha > 0, torch.full_like(alpha, z), torch.zeros_like(alpha))
    torch.testing.assert_close(r.depth[0], expected_depth, atol=1e-12, rtol=0)


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_front_to_back_and_termination_hand_computed(impl):
    # Three huge Gaussians (nearly constant over the image) on the axis at 3, 5, 7 m with
    # opacity 0.98: T = 0.02 after the first, 4e-4 after the second; the third would bring T
    # to 8e-6 <= 1e-4, so every pixel stops there. Input order is not depth order.
    dt = torch.float64
    n, o = 3, 0.98
    params = [
        torch.tensor([[0, 0, 7.0], [0, 0, 3.0], [0, 0, 5.0]], dtype=dt),
        torch.tensor([[1.0, 0, 0, 0]] * n, dtype=dt),
        torch.full((n, 3), 5000.0, dtype=dt),
        torch.full((n,), o, dtype=dt),
        torch.tensor([[1.0], [2.0], [3.0]], dtype=dt),
    ]
    viewmats, Ks = look_at_cameras(1)
    r = rasterize(*params, viewmats, Ks, WIDTH, HEIGHT, backend=impl)
    w_near, w_mid = o, (1 - o) * o
    tol = dict(atol=1e-6, rtol=0)
    torch.testing.assert_close(r.alpha, torch.full_like(r.alpha, w_near + w_mid), **tol)
    feat = torch.full_like(r.alpha, 2.0 * w_near + 3.0 * w_mid)
    torch.testing.assert_close(r.features[..., 0], feat, **tol)
    depth = torch.full_like(r.alpha, (3.0 * w_near + 5.0 * w_mid) / (w_near + w_mid))
    torch.testing.assert_close(r.depth, depth, **tol)


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_alpha_is_clamped_to_alpha_max(impl):
    dt = torch.float64
    params = [
        torch.tensor([[0, 0, 4.0]], dtype=dt),
        torch.tensor([[1.0, 0, 0, 0]], dtype=dt),
        torch.full((1, 3), 100.0, dtype=dt),
        torch.tensor([1.0], dtype=dt),
        torch.tensor([[1.0]], dtype=dt),
    ]
    viewmats, Ks = look_at_cameras(1)
    r = rasterize(*params, viewmats, Ks, WIDTH, HEIGHT, backend=impl)
    torch.testing.assert_close(r.alpha, torch.full_like(r.alpha, ALPHA_MAX), atol=1e-12, rtol=0)


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_empty_and_culled_scene_renders_zeros_with_zero_gradients(impl):
    params = random_scene(5, seed=3)
    params[0][:, 2] = -5.0  # every Gaussian behind the cameras
    out, g = grads(params, impl)
    for t in out:
        assert torch.count_nonzero(t) == 0
    for t in g:
        assert torch.count_nonzero(t) == 0


@pytest.mark.parametrize("impl", ALL_IMPLS)
def test_float32_close_to_float64(impl):
    p64 = random_scene(80, dim=3, seed=11)
    p32 = [p.float() for p in p64]
    r64 = render(p64, impl)
    r32 = render(p32, impl)
    for a, b in zip(r32, r64):
        assert a.dtype == torch.float32
        assert (a.double() - b).abs().max().item() < 2e-3


def test_depth_is_normalised_and_zero_where_empty():
    params = random_scene(30, seed=5, spread=1.0)
    r = render(params, "reference")
    alpha, depth = r.alpha[0], r.depth[0]  # camera 0: world z is camera z
    empty = alpha == 0
    assert empty.any() and (~empty).any()
    assert torch.all(depth[empty] == 0)
    # A convex combination of the Gaussians' depths, not an alpha-weighted sum.
    lo, hi = params[0][:, 2].min().item(), params[0][:, 2].max().item()
    assert depth[~empty].min().item() >= lo - 1e-9 and depth[~empty].max().item() <= hi + 1e-9
    assert r.alpha.max().item() < 1.0
