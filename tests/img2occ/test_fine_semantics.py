"""Fine per-pixel semantic head: its loss by hand, lifting at a finer resolution, the model."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES
from renderworld.img2occ import lift_features
from renderworld.img2occ.depth_lift import depth_bin_edges
from renderworld.img2occ.fine_semantics import pixel_class_loss
from tests.img2occ.conftest import make_model, tiny_config
from tests.img2occ.test_model import _hard_case

K = NUM_SEMANTIC_CLASSES


def _k(f: float, c: float) -> torch.Tensor:
    return torch.tensor([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]]).view(1, 1, 3, 3)


def test_pixel_class_loss_by_hand_and_balanced():
    # 2x2 logit map and 2x2 labels of the same camera: every label pixel samples its own
    # logit pixel exactly. Labels: class 4 three times, class 11 once.
    logits = torch.zeros(1, 1, K, 2, 2)
    logits[0, 0, 4] = 2.0
    labels = torch.tensor([[4, 4], [4, 11]]).view(1, 1, 2, 2)
    k = _k(2.0, 1.0)
    flat = logits[0, 0].permute(1, 2, 0).reshape(4, K)
    ce = F.cross_entropy(flat, labels.view(4), reduction="none")
    plain = pixel_class_loss(logits, k, k, labels)
    assert plain.item() == pytest.approx(ce.mean().item(), rel=1e-5)
    # p = 1: weights 1 / frequency (4: 1/0.75, 11: 1/0.25), normalised to mean 1.
    w = torch.tensor([1 / 0.75] * 3 + [4.0])
    w = w / w.mean()
    bal = pixel_class_loss(logits, k, k, labels, balance=1.0)
    assert bal.item() == pytest.approx((ce * w).sum().item() / w.sum().item(), rel=1e-5)
    assert bal.item() > plain.item()  # the rare, mispredicted class weighs more


def test_pixel_class_loss_without_labels_is_zero_with_a_graph():
    logits = torch.randn(1, 2, K, 3, 3, requires_grad=True)
    labels = torch.full((1, 2, 3, 3), 255)
    labels[0, 1, 0, 0] = FREE_ID  # "free" is not a class of the head either
    k = _k(3.0, 1.5).expand(1, 2, 3, 3)
    loss = pixel_class_loss(logits, k, k, labels, balance=0.5)
    assert loss.item() == 0.0 and loss.requires_grad
    with pytest.raises(ValueError, match="balance"):
        pixel_class_loss(logits, k, k, labels, balance=2.0)
    with pytest.raises(ValueError, match="logits/semantics"):
        pixel_class_loss(logits[:, :, :5], k, k, labels)


def test_lifting_samples_class_maps_of_another_resolution():
    # Constant class maps per camera: the lifted class mass is the same whether the map is
    # given at the feature resolution or four times finer.
    cam = torch.eye(4).view(1, 1, 4, 4)
    k = _k(2.0, 1.0)  # 2x2 feature map
    edges = depth_bin_edges(2, (1.0, 3.0))
    feats = torch.ones(1, 1, 3, 2, 2)
    cdf = torch.tensor([0.0, 0.5, 1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 2, 2)
    probs = torch.zeros(1, 1, K, 2, 2)
    probs[:, :, 7] = 1.0
    centres = torch.tensor([[0.1, 0.1, 2.0], [-0.2, 0.3, 2.2]])
    kw = dict(depth_cdf=cdf, edges=edges, radius=0.5)
    coarse = lift_features(feats, cam, k, centres, class_probs=probs, **kw)
    fine_probs = F.interpolate(probs[0], scale_factor=4, mode="nearest")[None]
    fine = lift_features(feats, cam, k, centres, class_probs=fine_probs, **kw)
    torch.testing.assert_close(fine.extras, coarse.extras)
    assert coarse.extras[0, 2 + 7].min() > 0


def test_model_with_fine_semantics_shapes_gradients_and_hard_cases(synthetic_batch):
    model = make_model("torch", depth_bins=8, depth_range=(0.5, 16.5), fine_semantics=True)
    model.train()
    h, w = model.cfg.input_size
    for case in ("all_free_targets", "no_lidar_at_all", "zero_images", "cameras_without_lidar"):
        batch = _hard_case(synthetic_batch, case)
        out = model(batch)
        assert out.fine_logits.shape == (1, 6, K, h // 2, w // 2)
        loss, logs = model.loss(batch, out)
        assert torch.isfinite(loss) and "loss_fine_sem" in logs, logs
        loss.backward()
        for name, p in model.named_parameters():
            assert p.grad is None or torch.isfinite(p.grad).all(), name
        if case == "cameras_without_lidar":
            assert model.fine_head.net[-1].weight.grad.abs().sum() > 0
            assert model.semantic_skip.grad is not None
        model.zero_grad()


def test_fine_semantics_config_is_validated():
    with pytest.raises(ValueError, match="fine_semantics: needs depth-aware lifting"):
        tiny_config(fine_semantics=True)
    with pytest.raises(ValueError, match="fine_class_balance"):
        tiny_config(depth_bins=8, fine_semantics=True, fine_class_balance=1.5)
