import math

import pytest
import torch

from renderworld.world import WorldModelOutput, WorldModelTargets, teacher_forcing_split
from renderworld.world import world_model_loss as loss_fn


def make_outputs(logits, disp):
    modes = disp[:, :, None].expand(-1, -1, 3, -1)
    return WorldModelOutput(logits=logits, displacement=disp, displacement_modes=modes)


def test_uniform_logits_give_log_k_per_codebook_averaged():
    b, t, h, w = 2, 3, 4, 4
    logits = [torch.zeros(b, t, 5, h, w), torch.zeros(b, t, 18, h, w)]
    tokens = torch.zeros(b, t, 2, h, w, dtype=torch.long)
    disp = torch.zeros(b, t, 2)
    out = loss_fn(make_outputs(logits, disp), WorldModelTargets(tokens, disp), lambda_l2=0.1)
    assert out["token_ce/0"].item() == pytest.approx(math.log(5), rel=1e-5)
    assert out["token_ce/1"].item() == pytest.approx(math.log(18), rel=1e-5)
    assert out["token_ce"].item() == pytest.approx((math.log(5) + math.log(18)) / 2, rel=1e-5)
    assert out["l2"].item() == pytest.approx(0.0, abs=1e-6)


def test_perfect_prediction_is_near_zero_and_l2_is_cumulative():
    b, t, h, w = 1, 4, 2, 2
    tokens = torch.randint(0, 5, (b, t, 1, h, w))
    logits = [torch.nn.functional.one_hot(tokens[:, :, 0], 5).permute(0, 1, 4, 2, 3) * 50.0]
    gt = torch.ones(b, t, 2)
    out = loss_fn(make_outputs(logits, gt.clone()), WorldModelTargets(tokens, gt))
    assert out["token_ce"].item() < 1e-6 and out["l2"].item() < 1e-6
    # A constant 0.5 m x-error per step: cumulative errors 0.5, 1.0, 1.5, 2.0 -> mean 1.25 m.
    pred = gt.clone()
    pred[..., 0] += 0.5
    out = loss_fn(make_outputs(logits, pred), WorldModelTargets(tokens, gt), lambda_l2=2.0)
    assert out["l2"].item() == pytest.approx(1.25, abs=1e-4)
    assert out["loss"].item() == pytest.approx(out["token_ce"].item() + 2.0 * 1.25, abs=1e-3)


def test_valid_mask_excludes_positions_and_all_invalid_is_defined():
    b, t = 1, 3
    tokens = torch.zeros(b, t, 1, 2, 2, dtype=torch.long)
    logits = [torch.zeros(b, t, 4, 2, 2, requires_grad=True)]
    pred = torch.zeros(b, t, 2, requires_grad=True)
    gt = torch.zeros(b, t, 2)
    gt[:, 2] = 100.0  # only the masked last position is wrong
    valid = torch.tensor([[True, True, False]])
    out = loss_fn(make_outputs(logits, pred), WorldModelTargets(tokens, gt, valid))
    assert out["l2"].item() == pytest.approx(0.0, abs=1e-6)
    none = torch.zeros_like(valid)
    out = loss_fn(make_outputs(logits, pred), WorldModelTargets(tokens, gt, none))
    out["loss"].backward()
    assert out["loss"].item() == 0.0
    assert torch.isfinite(pred.grad).all() and torch.isfinite(logits[0].grad).all()


def test_loss_validation():
    tokens = torch.zeros(1, 3, 1, 2, 2, dtype=torch.long)
    outputs = make_outputs([torch.zeros(1, 3, 4, 2, 2)], torch.zeros(1, 3, 2))
    with pytest.raises(ValueError, match="lambda_l2"):
        loss_fn(outputs, WorldModelTargets(tokens, torch.zeros(1, 3, 2)), lambda_l2=-1)
    with pytest.raises(ValueError, match="targets.displacements"):
        loss_fn(outputs, WorldModelTargets(tokens, torch.zeros(1, 2, 2)))
    with pytest.raises(ValueError, match="targets.tokens"):
        loss_fn(outputs, WorldModelTargets(tokens[:, :2], torch.zeros(1, 3, 2)))


def test_teacher_forcing_split_alignment():
    tokens = torch.arange(6).view(1, 6, 1, 1, 1).expand(1, 6, 1, 2, 2).contiguous()
    disp = torch.arange(5, dtype=torch.float32).view(1, 5, 1).expand(1, 5, 2)
    valid = torch.tensor([[True] * 5 + [False]])
    (inp_tok, inp_disp), tgt = teacher_forcing_split(tokens, disp, valid)
    assert inp_tok[0, :, 0, 0, 0].tolist() == [0, 1, 2, 3, 4]
    assert inp_disp[0, :, 0].tolist() == [0, 1, 2, 3]  # d[i] for i < L-2
    assert tgt.tokens[0, :, 0, 0, 0].tolist() == [1, 2, 3, 4, 5]  # frame i+1
    assert tgt.displacements[0, :, 0].tolist() == [0, 1, 2, 3, 4]  # d[i]
    assert tgt.valid.tolist() == [[True, True, True, True, False]]
    with pytest.raises(ValueError, match="displacements: expected"):
        teacher_forcing_split(tokens, disp[:, :-1])


def test_cumulative_from_accumulates_only_from_there():
    tokens = torch.zeros(1, 4, 1, 2, 2, dtype=torch.long)
    logits = [torch.zeros(1, 4, 3, 2, 2)]
    gt = torch.ones(1, 4, 2)
    pred = gt.clone()
    pred[..., 0] += 0.5
    out = loss_fn(make_outputs(logits, pred), WorldModelTargets(tokens, gt), cumulative_from=2)
    # per-step errors 0.5, 0.5 then cumulative 0.5, 1.0 -> mean 0.625 m
    assert out["l2"].item() == pytest.approx(0.625, abs=1e-5)
    with pytest.raises(ValueError, match="cumulative_from"):
        loss_fn(make_outputs(logits, pred), WorldModelTargets(tokens, gt), cumulative_from=4)
