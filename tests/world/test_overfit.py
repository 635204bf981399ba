"""A tiny world model must learn a moving blob better than copy-paste (real learning test)."""

import torch

from renderworld.constants import FREE_ID
from renderworld.world import WorldModel, WorldModelConfig, teacher_forcing_split, world_model_loss

H = W = 8
CAR = 4
STEPS = 120


def moving_blob_sequences(length=7):
    """2x2 blob of (air level 2, car) moving -1 cell/frame in x when the ego drives 2 m/step,
    standing still when the ego stands still; background (0, free)."""
    seqs, disps = [], []
    for y0 in (0, 3, 6):
        for speed in (0, 1):
            tok = torch.zeros(length, 2, H, W, dtype=torch.long)
            tok[:, 1] = FREE_ID
            for t in range(length):
                x0 = 6 - speed * t
                tok[t, 0, x0 : x0 + 2, y0 : y0 + 2] = 2
                tok[t, 1, x0 : x0 + 2, y0 : y0 + 2] = CAR
            seqs.append(tok)
            disps.append(torch.tensor([[2.0 * speed, 0.0]]).expand(length - 1, 2))
    return torch.stack(seqs), torch.stack(disps)


def test_tiny_world_model_learns_motion_better_than_copy_paste():
    torch.manual_seed(0)
    tokens, disps = moving_blob_sequences()
    (inp, inp_d), tgt = teacher_forcing_split(tokens, disps)
    cmd = torch.full((tokens.shape[0],), 2)
    cfg = WorldModelConfig(
        codebook_sizes=(3, 18), token_grid=(H, W), embed_dim=24, num_heads=2,
        num_scales=2, layers_per_scale=(1, 1), history_frames=2, future_frames=5,
    )  # fmt: skip
    model = WorldModel(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    first = None
    for _ in range(STEPS):
        out = model(inp, inp_d, cmd)
        loss = world_model_loss(out, tgt, lambda_l2=0.5, cumulative_from=1)
        opt.zero_grad()
        loss["loss"].backward()
        opt.step()
        first = loss["token_ce"].item() if first is None else first
    model.eval()
    with torch.no_grad():
        out = model(inp, inp_d, cmd)
    pred = torch.stack([lg.argmax(2) for lg in out.logits], dim=2)  # [B, T, G, h, w]
    # Positions >= 1 have seen a previous frame and displacement, so the motion is known.
    changed = tgt.tokens[:, 1:] != inp[:, 1:]  # cells copy-paste gets wrong
    assert changed.sum() > 100
    model_acc = (pred[:, 1:] == tgt.tokens[:, 1:])[changed].float().mean().item()
    copy_acc = (inp[:, 1:] == tgt.tokens[:, 1:])[changed].float().mean().item()
    overall = (pred[:, 1:] == tgt.tokens[:, 1:]).float().mean().item()
    assert copy_acc == 0.0
    assert model_acc > 0.9, (model_acc, first, loss["token_ce"].item())
    assert overall > 0.99
    # The ego head learned the two speeds too (position 0 has no previous step: ambiguous).
    err = (out.displacement[:, 1:] - tgt.displacements[:, 1:]).abs().max().item()
    assert err < 0.5
