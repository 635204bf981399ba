"""Img2Occ model: Gaussian attribute ranges, gradients through rendering, hard cases, config."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES
from renderworld.geometry import VoxelGrid
from renderworld.img2occ import Img2Occ, Img2OccConfig
from tests.img2occ._synthetic import TEST_GRID
from tests.img2occ.conftest import make_model, tiny_config


def _model(backend: str = "torch", **overrides) -> Img2Occ:
    return make_model(backend, **overrides)


def _batch2(batch: dict) -> dict:
    """B = 2 copies of the synthetic batch (second one with the cameras rotated)."""
    out = {}
    for k, v in batch.items():
        if isinstance(v, torch.Tensor):
            v2 = v.clone()
            if v.ndim >= 2 and v.shape[1] == 6 and k != "occ":
                v2 = v2[:, [1, 2, 3, 4, 5, 0]]
            out[k] = torch.cat([v, v2])
    return out


def test_gaussian_attributes_shapes_and_ranges(synthetic_batch):
    model = _model()
    batch = _batch2(synthetic_batch)
    out = model(batch, render=False)
    g = out.gaussians
    x, y, z = TEST_GRID.shape
    v = x * y * z
    assert g.means.shape == (2, v, 3) and g.scales.shape == (2, v, 3)
    assert g.quats.shape == (2, v, 4) and g.opacities.shape == (2, v)
    assert g.logits.shape == (2, v, NUM_SEMANTIC_CLASSES)
    assert out.visibility.shape == (2, x, y, z)
    grid = VoxelGrid(TEST_GRID)
    centres = torch.tensor(grid.centres().reshape(-1, 3), dtype=torch.float32)
    half = torch.tensor(grid.voxel_size / 2, dtype=torch.float32)
    assert ((g.means - centres).abs() <= half + 1e-5).all()
    edge = float(grid.voxel_size.min())
    lo, hi = model.cfg.scale_range
    assert (g.scales >= lo * edge - 1e-6).all() and (g.scales <= hi * edge + 1e-6).all()
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(2, v), atol=1e-5, rtol=0)
    assert ((g.opacities > 0) & (g.opacities < 1)).all()
    # init: opacity near init_opacity, rotation near identity
    assert abs(g.opacities.mean().item() - model.cfg.init_opacity) < 0.05
    assert g.quats[..., 0].mean().item() > 0.9


def test_extreme_head_outputs_stay_in_range(synthetic_batch):
    model = _model()
    with torch.no_grad():
        model.head.out.bias.mul_(1e4)  # saturate every activation
        model.head.out.weight.mul_(1e3)
    g = model(synthetic_batch, render=False).gaussians
    grid = VoxelGrid(TEST_GRID)
    edge = float(grid.voxel_size.min())
    for t in (g.means, g.quats, g.scales, g.opacities, g.logits):
        assert torch.isfinite(t).all()
    assert (g.scales <= model.cfg.scale_range[1] * edge + 1e-5).all()
    assert (g.quats.norm(dim=-1) <= 1 + 1e-5).all()


@pytest.mark.parametrize("backend", ["torch", "reference", "dense"])
def test_gradients_reach_encoder_through_rendering(synthetic_batch, backend):
    model = _model(backend)
    model.train()
    out = model(synthetic_batch)
    assert out.views.features.shape == (1, 3, 18, 32, NUM_SEMANTIC_CLASSES)
    assert out.view_index.shape == (1, 3)
    loss, logs = model.loss(synthetic_batch, out)
    assert torch.isfinite(loss) and set(logs) >= {"loss", "loss_sem", "loss_depth"}
    loss.backward()
    first = model.encoder.trunk[0][0].weight.grad
    assert first is not None and torch.isfinite(first).all() and first.abs().sum() > 0
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_eval_renders_every_camera_and_train_a_subset(synthetic_batch):
    model = _model(views_per_step=2)
    model.train()
    idx = model(synthetic_batch).view_index
    assert idx.shape == (1, 2) and len(set(idx[0].tolist())) == 2
    model.eval()
    with torch.no_grad():
        assert model(synthetic_batch).view_index[0].tolist() == list(range(6))


def _hard_case(batch: dict, case: str) -> dict:
    b = dict(batch)
    if case == "all_free_targets":
        b["semantics"] = torch.full_like(batch["semantics"], FREE_ID)
        b["depth"] = torch.zeros_like(batch["depth"])
        b["occ"] = torch.full_like(batch["occ"], FREE_ID)
    elif case == "cameras_without_lidar":
        b["semantics"] = batch["semantics"].clone()
        b["depth"] = batch["depth"].clone()
        b["semantics"][:, :4] = 255
        b["depth"][:, :4] = 0
    elif case == "no_lidar_at_all":
        b["semantics"] = torch.full_like(batch["semantics"], 255)
        b["depth"] = torch.zeros_like(batch["depth"])
    elif case == "zero_images":
        b["images"] = torch.zeros_like(batch["images"])
    return b


@pytest.mark.parametrize(
    "case, backend",
    [
        ("all_free_targets", "torch"),
        ("cameras_without_lidar", "torch"),
        ("no_lidar_at_all", "torch"),
        ("zero_images", "torch"),
        ("all_free_targets", "reference"),
        ("zero_images", "dense"),
    ],
)
def test_hard_cases_finite_forward_and_backward(synthetic_batch, case, backend):
    model = _model(backend, views_per_step=None)
    model.train()
    batch = _hard_case(synthetic_batch, case)
    out = model(batch)
    loss, logs = model.loss(batch, out)
    assert torch.isfinite(loss), logs
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


def test_everything_pruned_still_trains(synthetic_batch):
    model = _model(prune_opacity=0.99)
    out = model(synthetic_batch)
    assert out.views.num_rendered.tolist() == [0]
    assert out.views.alpha.abs().sum().item() == 0.0
    loss, _ = model.loss(synthetic_batch, out)
    assert torch.isfinite(loss) and loss.requires_grad
    loss.backward()


def test_default_renderer_is_the_splat_rasterizer(synthetic_batch, monkeypatch):
    import renderworld.splat

    calls = []
    real = renderworld.splat.rasterize

    def spy(**kw):
        calls.append(kw["backend"])
        return real(**kw)

    monkeypatch.setattr(renderworld.splat, "rasterize", spy)
    model = Img2Occ(tiny_config(render_backend="torch"))
    model(synthetic_batch)
    assert calls == ["torch"]


def test_dense_standin_agrees_with_splat_reference(synthetic_batch):
    ref = _model("reference")
    with torch.no_grad():  # varied opacities per height so that occlusion matters
        ref.head.out.bias.view(4, -1)[:, 10] = torch.tensor([2.0, -1.0, 0.0, -3.0])
    dense = _model("dense")
    dense.load_state_dict(ref.state_dict())
    ref.eval(), dense.eval()
    with torch.no_grad():
        a, b = ref(synthetic_batch).views, dense(synthetic_batch).views
    # measured max differences 0.014 (alpha), 9e-4 (features): splat truncates footprints
    # at an opacity-aware 3-sigma radius, the stand-in never truncates.
    torch.testing.assert_close(a.alpha, b.alpha, atol=0.03, rtol=0)
    torch.testing.assert_close(a.features, b.features, atol=3e-3, rtol=0)
    valid = (a.alpha > 0.5) & (b.alpha > 0.5)
    torch.testing.assert_close(a.depth[valid], b.depth[valid], atol=0.15, rtol=0)


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_pruning_at_one_over_255_is_lossless(synthetic_batch, backend):
    base = _model(backend, prune_opacity=0.0)
    with torch.no_grad():  # spread opacities so that some fall under 1/255
        base.head.out.bias.view(4, -1)[:, 10] = torch.tensor([-9.0, -7.0, 0.0, 2.0])
    pruned = _model(backend, prune_opacity=1.0 / 255.0)
    pruned.load_state_dict(base.state_dict())
    base.eval(), pruned.eval()
    with torch.no_grad():
        a, b = base(synthetic_batch), pruned(synthetic_batch)
    assert b.views.num_rendered.item() < a.views.num_rendered.item()
    torch.testing.assert_close(a.views.features, b.views.features, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(a.views.alpha, b.views.alpha, atol=1e-5, rtol=1e-4)


def test_adjacent_frame_supervision(synthetic_batch):
    batch = dict(synthetic_batch)
    for k in ("cam_to_ego", "render_intrinsics", "depth", "semantics"):
        batch["adj_" + k] = torch.cat([synthetic_batch[k], synthetic_batch[k]], dim=1)
    model = _model(adjacent_frames=True, adjacent_views_per_step=2)
    model.train()
    out = model(batch)
    assert out.adj_index.shape == (1, 2)
    loss, logs = model.loss(batch, out)
    assert "loss_adj_sem" in logs and "loss_adj_depth" in logs
    plain = _model(adjacent_frames=False)
    assert plain(batch).adj_views is None
    loss.backward()


def test_readout_uses_stored_threshold_and_checkpoint_keeps_it(synthetic_batch):
    model = _model()
    model.eval()
    with torch.no_grad():
        out = model(synthetic_batch, render=False)
    op = out.gaussians.opacities
    t = float(op.median())
    model.set_threshold(t)
    occ = model.readout(out)
    assert occ.dtype == torch.uint8 and occ.shape == (1, *TEST_GRID.shape)
    occupied = (occ != FREE_ID).view(1, -1)
    assert torch.equal(occupied, op > t)
    cls = out.gaussians.logits.argmax(-1)
    assert torch.equal(occ.view(1, -1)[occupied].long(), cls[occupied])
    state = model.state_dict()
    assert float(state["occupancy_threshold"]) == pytest.approx(t)
    fresh = _model()
    assert float(fresh.occupancy_threshold) == pytest.approx(0.5)
    fresh.load_state_dict(state)
    assert float(fresh.occupancy_threshold) == pytest.approx(t)
    with pytest.raises(ValueError, match="threshold"):
        model.set_threshold(1.5)


def test_input_validation(synthetic_batch):
    model = _model()
    with pytest.raises(ValueError, match=r"images: expected \[B, C, 3, 48, 88\]"):
        model({**synthetic_batch, "images": synthetic_batch["images"][..., :40]})
    with pytest.raises(ValueError, match="batch: missing key"):
        model({"images": synthetic_batch["images"]})
    with pytest.raises(TypeError, match="batch: expected a dict"):
        model([synthetic_batch["images"]])
    out = model(synthetic_batch, render=False)
    with pytest.raises(ValueError, match="no rendered views"):
        model.loss(synthetic_batch, out)
    small = {**synthetic_batch, "depth": synthetic_batch["depth"][..., :10]}
    with pytest.raises(ValueError, match="render_size"):
        model.loss(small, model(synthetic_batch))


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"grid": "nope"}, "grid: unknown grid"),
        ({"input_size": (50, 88)}, "input_size: expected sizes divisible"),
        ({"render_size": (0, 32)}, "render_size: expected a positive int"),
        ({"feature_stride": 2}, "feature_stride: expected 4, 8 or 16"),
        ({"encoder_channels": (8, 16)}, "encoder_channels: expected at least 3"),
        ({"scale_range": (0.5, 0.2)}, "scale_range"),
        ({"init_opacity": 1.0}, "init_opacity"),
        ({"prune_opacity": -0.1}, "prune_opacity"),
        ({"views_per_step": 0}, "views_per_step"),
        ({"depth_weight": float("nan")}, "depth_weight"),
        ({"near": 5.0, "far": 1.0}, "near/far"),
        ({"timm_weights": "/x.pt"}, "timm_weights: given without timm_backbone"),
        ({"head_blocks": -1}, "head_blocks"),
    ],
)
def test_config_validation_names_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        tiny_config(**kw)


def test_default_config_is_the_coarse_grid():
    cfg = Img2OccConfig()
    assert cfg.grid.name == "coarse" and cfg.feature_size == (32, 88)
    assert np.isclose(cfg.scale_range[0], 0.2) and np.isclose(cfg.scale_range[1], 0.8)


def test_backprojected_loss_trains_finite_on_hard_cases(synthetic_batch):
    model = _model("torch", views_per_step=None, backproject_weight=2.0)
    model.train()
    for case in ("all_free_targets", "no_lidar_at_all", "zero_images"):
        batch = _hard_case(synthetic_batch, case)
        loss, logs = model.loss(batch, model(batch))
        assert torch.isfinite(loss) and "loss_bp_occ" in logs and "loss_bp_sem" in logs, logs
        loss.backward()
        for name, p in model.named_parameters():
            assert p.grad is None or torch.isfinite(p.grad).all(), name
        model.zero_grad()


def test_depth_l1_weight_adds_its_term_to_the_loss(synthetic_batch):
    """``depth_l1_weight`` (on in the mini experiment, off in the paper's loss) adds exactly
    weight x the relative-depth L1 of the rendered views to the training loss."""
    torch.manual_seed(0)
    plain = make_model("torch").eval()  # eval: every camera rendered, no random view subset
    weighted = make_model("torch", depth_l1_weight=2.0).eval()
    weighted.load_state_dict(plain.state_dict())
    loss, logs = plain.loss(synthetic_batch, plain(synthetic_batch))
    loss_w, logs_w = weighted.loss(synthetic_batch, weighted(synthetic_batch))
    assert logs_w["loss_depth_l1"] > 0.01
    torch.testing.assert_close(logs_w["loss_depth_l1"], logs["loss_depth_l1"])
    torch.testing.assert_close(loss_w - loss, 2.0 * logs["loss_depth_l1"], rtol=1e-5, atol=1e-6)
