"""Img2Occ trains under bf16 autocast: networks in bf16, geometry / rendering / losses in float32.

CPU autocast stands in for CUDA's here (same policy, renderworld.precision). Tolerance against
the float32 step on the same weights and views: loss within 1 % (relative), gradient cosine
>= 0.98 over all parameters (measured 2026-11-24: <= 0.11 % and >= 0.993).
"""

from __future__ import annotations

import copy

import pytest
import torch

from renderworld.splat import rasterize
from tests.img2occ.conftest import make_model

LOSS_RTOL = 1e-2
GRAD_COSINE = 0.98


def _step(model, batch, amp: bool):
    model = copy.deepcopy(model)
    torch.manual_seed(1)  # same mirrored / rendered views in both runs
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
        b = model.augment(batch)
        out = model(b)
        loss, _ = model.loss(b, out)
    loss.backward()
    grads = {n: p.grad for n, p in model.named_parameters()}
    return loss.detach(), grads, out


CONFIGS = {
    "paper": {},
    "mini_recipe": dict(
        depth_bins=8,
        fine_semantics=True,
        depth_l1_weight=2.0,
        backproject_weight=2.0,
        mirror_prob=0.5,
        adjacent_frames=0,
    ),
    "3d_supervision": dict(depth_bins=8, supervision="3d"),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_bf16_step_is_finite_and_close_to_float32(synthetic_batch, name):
    torch.manual_seed(0)
    model = make_model("torch", **CONFIGS[name]).train()
    seen = []
    model.head.out.register_forward_hook(lambda m, i, o: seen.append(o.dtype))
    l32, g32, _ = _step(model, synthetic_batch, amp=False)
    seen.clear()
    l16, g16, out = _step(model, synthetic_batch, amp=True)
    assert seen and seen[0] == torch.bfloat16  # the networks really ran in bf16
    g = out.gaussians
    for t in (g.means, g.quats, g.scales, g.opacities, g.logits):
        assert t.dtype == torch.float32  # geometry handed to the rasterizer in float32
    assert l16.dtype == torch.float32 and torch.isfinite(l16)
    assert abs(float(l16 - l32)) <= LOSS_RTOL * abs(float(l32))
    for n, gr in g16.items():
        assert gr is not None and gr.dtype == torch.float32 and torch.isfinite(gr).all(), n
    flat32 = torch.cat([g32[n].flatten() for n in g32])
    flat16 = torch.cat([g16[n].flatten() for n in g32])
    assert float(torch.nn.functional.cosine_similarity(flat32, flat16, dim=0)) >= GRAD_COSINE


def test_readout_under_autocast_reads_float32_gaussians(synthetic_batch):
    """Eval under autocast (validation): Gaussians and readout labels come out of float32."""
    model = make_model("torch", depth_bins=8).eval()
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(synthetic_batch, render=False)
        labels = model.readout(out)
    assert out.gaussians.means.dtype == torch.float32
    assert labels.shape[1:] == tuple(model.cfg.grid.shape)


def test_rasterize_under_autocast_takes_mixed_dtypes_and_renders_float32():
    torch.manual_seed(0)
    n = 50
    means = torch.randn(n, 3) * 0.5 + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(n, 4)
    scales = torch.rand(n, 3) * 0.2 + 0.05
    opac = torch.rand(n) * 0.8
    feats = torch.rand(n, 4)
    view = torch.eye(4)[None]
    k = torch.tensor([[[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]])
    ref = rasterize(means, quats, scales, opac, feats, view, k, 32, 24, backend="torch")
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = rasterize(
            means, quats.bfloat16(), scales.bfloat16(), opac, feats.bfloat16(), view, k, 32, 24,
            backend="torch",
        )  # fmt: skip
    assert out.features.dtype == torch.float32
    # Only the inputs' bf16 rounding differs (8-bit mantissa: ~0.4 %).
    torch.testing.assert_close(out.alpha, ref.alpha, atol=2e-2, rtol=0)
    with pytest.raises(TypeError, match=r"scales: expected dtype torch.float32"):
        rasterize(means, quats, scales.double(), opac, feats, view, k, 32, 24)
