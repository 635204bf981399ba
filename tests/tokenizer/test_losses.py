import math

import pytest
import torch
import torch.nn.functional as F

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer import NON_AIR_IDS, combine_air_mask, scores_to_occupancy
from renderworld.tokenizer.losses import air_mask_head_loss, softmax_head_loss

SHAPE = (2, 4, 4, 3)


def _air_mask_inputs(seed=0, dtype=torch.float32, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    a = (torch.randn(SHAPE, generator=g, dtype=dtype) * scale).requires_grad_(True)
    n = (torch.randn(*SHAPE, 17, generator=g, dtype=dtype) * scale).requires_grad_(True)
    return a, n


def test_combined_distribution_is_normalised_and_factorised():
    a, n = _air_mask_inputs(dtype=torch.float64)
    lp = combine_air_mask(a, n)
    assert lp.shape == (*SHAPE, NUM_OCC3D_CLASSES)
    assert torch.allclose(lp.logsumexp(-1), torch.zeros(SHAPE, dtype=torch.float64), atol=1e-12)
    p_free = torch.sigmoid(a)
    assert torch.allclose(lp[..., FREE_ID].exp(), p_free)
    assert torch.allclose(
        lp[..., list(NON_AIR_IDS)].exp(), (1 - p_free)[..., None] * n.softmax(-1), atol=1e-12
    )
    # Extreme logits stay finite (log(1 - sigmoid) computed as logsigmoid(-a)).
    big = combine_air_mask(torch.full((3,), 1e4), torch.zeros(3, 17))
    assert torch.isfinite(big).all()


def test_air_mask_decision_rule_is_eq_6_13():
    # p(free) = 0.4 but the non-air mass is spread: argmax would say free, the mask says car.
    a = torch.tensor([math.log(0.4 / 0.6), 2.0, -3.0])
    n = torch.zeros(3, 17)
    n[:, 4] = 0.5  # car is the best non-air class, with ~1/17.6 of the non-air mass
    lp = combine_air_mask(a, n)
    assert lp[0].argmax() == FREE_ID
    assert scores_to_occupancy(lp, air_mask_head=True).tolist() == [4, FREE_ID, 4]
    assert scores_to_occupancy(lp, air_mask_head=False).tolist() == [FREE_ID, FREE_ID, 4]


def test_air_mask_loss_decomposes_into_branch_terms_float64():
    a, n = _air_mask_inputs(dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    target = torch.randint(0, NUM_OCC3D_CLASSES, SHAPE, generator=g)
    lp = combine_air_mask(a, n)
    out = air_mask_head_loss(a, n, lp, target, ce_weight=2.0, lovasz_weight=0.5)
    free = target == FREE_ID
    bce = F.binary_cross_entropy_with_logits(a, free.double())
    ce_na = F.cross_entropy(n[~free], target[~free])  # NON_AIR_IDS is 0..16 in order here
    assert out["air"].item() == pytest.approx(bce.item(), rel=1e-6)
    assert out["non_air"].item() == pytest.approx(ce_na.item(), rel=1e-6)
    assert out["recon"].item() == pytest.approx(
        2.0 * (bce + ce_na).item() + 0.5 * out["lovasz"].item(), rel=1e-6
    )
    # The summed (not averaged) branch NLL equals the 18-way NLL of the combined distribution.
    nll = F.nll_loss(lp.reshape(-1, 18), target.reshape(-1), reduction="sum")
    bce_sum = F.binary_cross_entropy_with_logits(a, free.double(), reduction="sum")
    summed = bce_sum + F.cross_entropy(n[~free], target[~free], reduction="sum")
    assert nll.item() == pytest.approx(summed.item(), rel=1e-9)


def _all_finite(losses, *leaves):
    total = sum(v for k, v in losses.items() if k == "recon")
    total.backward()
    assert all(torch.isfinite(v) for v in losses.values())
    assert all(x.grad is not None and torch.isfinite(x.grad).all() for x in leaves)


@pytest.mark.parametrize("scale", [1.0, 1e3])
def test_all_free_volume_and_absent_classes_stay_finite(scale):
    target = torch.full(SHAPE, FREE_ID)
    a, n = _air_mask_inputs(scale=scale)
    out = air_mask_head_loss(a, n, combine_air_mask(a, n), target)
    assert out["non_air"].item() == 0.0
    _all_finite(out, a, n)
    logits = (torch.randn(*SHAPE, 18) * scale).requires_grad_(True)
    _all_finite(softmax_head_loss(logits, target, present_only=False), logits)
    # Only two classes present, the rest absent; class weights with zeros.
    target2 = torch.where(torch.rand(SHAPE) < 0.5, 4, FREE_ID)
    w = torch.ones(18)
    w[:10] = 0.0
    a, n = _air_mask_inputs(scale=scale)
    _all_finite(air_mask_head_loss(a, n, combine_air_mask(a, n), target2, class_weights=w), a, n)
    logits = (torch.randn(*SHAPE, 18) * scale).requires_grad_(True)
    _all_finite(softmax_head_loss(logits, target2, class_weights=w), logits)


def test_class_weights_change_the_ce():
    logits = torch.randn(*SHAPE, 18)
    target = torch.randint(0, 18, SHAPE)
    w = torch.rand(18) + 0.1
    plain = softmax_head_loss(logits, target)["ce"]
    weighted = softmax_head_loss(logits, target, class_weights=w)["ce"]
    ref = F.cross_entropy(logits.reshape(-1, 18), target.reshape(-1), weight=w)
    assert float(weighted) == pytest.approx(float(ref)) and float(weighted) != float(plain)
