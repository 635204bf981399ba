"""Losses: Pearson depth against numpy, degenerate cases finite, semantic NLL semantics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES
from renderworld.img2occ import (
    IGNORE_LABEL,
    pearson_depth_loss,
    relative_depth_l1_loss,
    rendered_distribution,
    semantic_nll_loss,
)

K = NUM_SEMANTIC_CLASSES


@pytest.mark.parametrize("seed", range(5))
def test_pearson_equals_numpy_corrcoef(seed):
    rng = np.random.default_rng(seed)
    n, h, w = 3, 7, 9
    target = rng.uniform(1, 60, (n, h, w))
    target[rng.random((n, h, w)) < 0.4] = 0.0  # pixels without LiDAR
    rendered = 0.5 * target + rng.normal(0, 5 + seed, (n, h, w)) + 10
    want = []
    for i in range(n):
        m = target[i] > 0
        want.append(1 - np.corrcoef(rendered[i][m], target[i][m])[0, 1])
    got = pearson_depth_loss(torch.tensor(rendered), torch.tensor(target))
    np.testing.assert_allclose(float(got), np.mean(want), rtol=1e-5, atol=1e-6)


def test_pearson_perfect_and_anti_correlation():
    t = torch.linspace(1, 30, 20).view(1, 4, 5)
    assert float(pearson_depth_loss(2 * t + 3, t)) == pytest.approx(0.0, abs=1e-5)
    assert float(pearson_depth_loss(-t, t)) == pytest.approx(2.0, abs=1e-5)


def _finite_grad(rendered, loss):
    loss.backward()
    assert torch.isfinite(loss)
    assert rendered.grad is not None and torch.isfinite(rendered.grad).all()


@pytest.mark.parametrize("case", ["constant_target", "single_pixel", "no_pixels", "all_const"])
def test_pearson_degenerate_cases_are_zero_and_finite(case):
    rendered = torch.rand(2, 5, 6, dtype=torch.float64).mul(20).requires_grad_(True)
    target = torch.zeros(2, 5, 6, dtype=torch.float64)
    if case == "constant_target":
        target[:, ::2] = 7.3
    elif case == "single_pixel":
        target[0, 2, 3] = 11.0
        target[1, 4, 0] = 3.0
    elif case == "all_const":
        target[:] = 5.0
        rendered = torch.full((2, 5, 6), 4.0, dtype=torch.float64, requires_grad=True)
    loss = pearson_depth_loss(rendered, target)
    assert loss.requires_grad
    assert loss.item() == 0.0
    _finite_grad(rendered, loss)


def test_pearson_constant_rendering_has_bounded_gradient():
    # A constant render (e.g. nothing drawn) against a varying target: loss 1, finite grads.
    rendered = torch.zeros(1, 4, 4, requires_grad=True)
    target = torch.arange(1.0, 17.0).view(1, 4, 4)
    loss = pearson_depth_loss(rendered, target)
    assert loss.item() == pytest.approx(1.0)
    _finite_grad(rendered, loss)
    assert rendered.grad.abs().max() < 1e4


def test_pearson_skips_degenerate_images_in_the_mean():
    t_good = torch.linspace(1, 10, 12).view(1, 3, 4)
    target = torch.cat([t_good, torch.full((1, 3, 4), 2.0)])
    rendered = torch.cat([-t_good, torch.rand(1, 3, 4)])
    assert float(pearson_depth_loss(rendered, target)) == pytest.approx(2.0, abs=1e-5)


def test_pearson_validates_shapes():
    with pytest.raises(ValueError, match="rendered/target"):
        pearson_depth_loss(torch.zeros(1, 2, 3), torch.zeros(1, 3, 2))
    with pytest.raises(ValueError, match="mask"):
        pearson_depth_loss(torch.zeros(1, 2, 3), torch.zeros(1, 2, 3), torch.zeros(2, 3) > 0)


def test_relative_l1_value_and_empty():
    r = torch.tensor([[[2.0, 5.0, 9.0]]], requires_grad=True)
    t = torch.tensor([[[4.0, 0.0, 10.0]]])
    assert relative_depth_l1_loss(r, t).item() == pytest.approx((0.5 + 0.1) / 2)
    empty = relative_depth_l1_loss(r, torch.zeros_like(t))
    assert empty.item() == 0.0 and empty.requires_grad
    _finite_grad(r, empty)


def _render_like(n=2, h=3, w=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    probs = torch.softmax(torch.randn(n, h, w, K, generator=g), -1)
    alpha = torch.rand(n, h, w, generator=g) * 0.98
    return (probs * alpha[..., None]).requires_grad_(True), alpha.requires_grad_(True)


def test_semantic_nll_matches_manual_distribution():
    feats, alpha = _render_like()
    labels = torch.randint(0, K, (2, 3, 4))
    labels[0, 0, 0] = IGNORE_LABEL
    labels[1, 2, 3] = FREE_ID  # "ray escaped" supervises transmittance
    got = semantic_nll_loss(feats, alpha, labels, eps=1e-6)
    dist = torch.cat([feats, (1 - alpha)[..., None]], -1).detach().numpy()
    lab, want = labels.numpy(), []
    for idx in np.ndindex(lab.shape):
        if lab[idx] != IGNORE_LABEL:
            want.append(-np.log(dist[idx][lab[idx]] / dist[idx].sum() + 1e-6))
    np.testing.assert_allclose(got.item(), np.mean(want), rtol=1e-5)
    d = rendered_distribution(feats, alpha)
    torch.testing.assert_close(d.sum(-1), torch.ones(2, 3, 4))


def test_semantic_nll_pushes_opacity_where_lidar_saw_a_surface():
    # Nearly transparent pixel labelled "car": the loss is high and raising the rendered
    # car probability (i.e. opacity along the ray) lowers it.
    feats = torch.full((1, 1, 1, K), 1e-4 / K, requires_grad=True)
    alpha = torch.full((1, 1, 1), 1e-4, requires_grad=True)
    labels = torch.tensor([[[4]]])
    loss = semantic_nll_loss(feats, alpha, labels)
    assert loss.item() > 5
    loss.backward()
    assert feats.grad[0, 0, 0, 4] < 0  # more car mass -> lower loss
    assert alpha.grad[0, 0, 0] < 0  # more alpha -> less "escaped" mass -> lower loss
    assert torch.isfinite(feats.grad).all()


def test_semantic_nll_no_labels_is_zero_with_graph():
    feats, alpha = _render_like()
    labels = torch.full((2, 3, 4), IGNORE_LABEL)
    loss = semantic_nll_loss(feats, alpha, labels)
    assert loss.item() == 0.0 and loss.requires_grad
    loss.backward()
    assert torch.isfinite(feats.grad).all() and torch.isfinite(alpha.grad).all()


def test_semantic_nll_validates():
    feats, alpha = _render_like()
    with pytest.raises(ValueError, match="labels: expected ids"):
        semantic_nll_loss(feats, alpha, torch.full((2, 3, 4), 40))
    with pytest.raises(ValueError, match="features: expected 17 class channels"):
        semantic_nll_loss(feats[..., :5], alpha, torch.zeros(2, 3, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="alpha/labels"):
        semantic_nll_loss(feats, alpha[:1], torch.zeros(2, 3, 4, dtype=torch.long))
