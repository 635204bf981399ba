"""The world model trains under bf16 autocast: the transformer in bf16, the trajectory head and
the loss (token cross-entropy, cumulative trajectory L2) in float32 (renderworld.precision).

Tolerance against the float32 step on the same weights: loss within 1 % (relative), gradient
cosine >= 0.98 (measured 2026-11-24: loss 0.01 %, cosine 0.99999).
"""

from __future__ import annotations

import copy

import torch

from renderworld.world import teacher_forcing_split, world_model_loss

from .test_model import random_inputs, tiny_model


def _step(model, tokens, disp, cmd, amp: bool):
    model = copy.deepcopy(model)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
        (inp, inp_disp), targets = teacher_forcing_split(tokens, disp)
        out = model(inp, inp_disp, cmd)
        terms = world_model_loss(out, targets, lambda_l2=0.1, cumulative_from=2)
    terms["loss"].backward()
    return out, terms["loss"].detach(), {n: p.grad for n, p in model.named_parameters()}


def test_bf16_step_is_finite_and_close_to_float32():
    model = tiny_model().train()
    tokens, disp, cmd = random_inputs(b=2, t=6)
    _, l32, g32 = _step(model, tokens, disp, cmd, amp=False)
    out, l16, g16 = _step(model, tokens, disp, cmd, amp=True)
    assert out.logits[0].dtype == torch.bfloat16  # the transformer really ran in bf16
    assert out.displacement.dtype == torch.float32  # metres stay float32
    assert torch.isfinite(l16) and abs(float(l16 - l32)) <= 1e-2 * abs(float(l32)), (l16, l32)
    named = [n for n, g in g32.items() if g is not None]
    for n in named:
        assert g16[n] is not None and torch.isfinite(g16[n]).all(), n
    flat32 = torch.cat([g32[n].flatten() for n in named])
    flat16 = torch.cat([g16[n].flatten() for n in named])
    cos = float(torch.nn.functional.cosine_similarity(flat32, flat16, dim=0))
    assert cos >= 0.98, cos
