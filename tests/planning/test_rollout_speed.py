"""The rollout's shortcuts give the reference's results: last-position logits, buffered KV cache."""

import pytest
import torch

from renderworld.world import WorldModel, WorldModelCache, WorldModelConfig


def model_and_inputs(t=5, seed=0):
    torch.manual_seed(seed)
    cfg = WorldModelConfig(
        codebook_sizes=(8, 6), token_grid=(6, 5), embed_dim=16, num_heads=2, num_scales=3,
        layers_per_scale=(1, 1, 1),
    )  # fmt: skip
    model = WorldModel(cfg).eval()
    torch.nn.init.normal_(model.ego_head.weight, std=0.3)
    tokens = torch.stack([torch.randint(0, k, (2, t, 6, 5)) for k in (8, 6)], 2)
    disp = torch.randn(2, t - 1, 2) * 3
    return model, tokens, disp, torch.tensor([0, 2])


def test_last_only_equals_the_full_call_at_the_last_position():
    model, tokens, disp, cmd = model_and_inputs()
    with torch.no_grad():
        full = model(tokens, disp, cmd)
        last = model(tokens, disp, cmd, last_only=True)
    for lf, ll in zip(full.logits, last.logits):
        assert ll.shape[1] == 1
        torch.testing.assert_close(ll[:, 0], lf[:, -1], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(last.displacement, full.displacement)


@pytest.mark.parametrize("first", [1, 3, 4])
def test_logits_from_equal_the_full_call_and_its_gradients(first):
    """Logits of the later positions only (the pose-warp loss scores the future frames):
    the full call's values there, and the same gradients for a loss that reads only them."""
    model, tokens, disp, cmd = model_and_inputs(t=5, seed=2)
    model.train()
    full = model(tokens, disp, cmd)
    part = model(tokens, disp, cmd, logits_from=first)
    grads = []
    for logits in ([lg[:, first:] for lg in full.logits], part.logits):
        model.zero_grad()
        sum((lg.square().mean() for lg in logits), torch.zeros(())).backward()
        grads.append({n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    for lf, lp in zip(full.logits, part.logits):
        assert lp.shape[1] == 5 - first
        torch.testing.assert_close(lp, lf[:, first:], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(part.displacement, full.displacement)
    assert grads[0].keys() == grads[1].keys()
    for name in grads[0]:
        torch.testing.assert_close(grads[1][name], grads[0][name], rtol=1e-5, atol=1e-7)


def test_logits_from_is_refused_with_a_cache_or_outside_the_window():
    model, tokens, disp, cmd = model_and_inputs(t=5)
    for bad, cache in ((5, None), (-1, None), (2, WorldModelCache())):
        with pytest.raises(ValueError, match=r"logits_from: expected a position in 1\.\.4"):
            model(tokens, disp, cmd, cache=cache, logits_from=bad)


@pytest.mark.parametrize("chunks", [(5, 1, 1, 1), (3, 2, 1, 2), (1, 1, 1, 1, 1, 1, 1, 1)])
def test_cached_pieces_with_last_only_equal_the_whole_window(chunks):
    model, tokens, disp, cmd = model_and_inputs(t=sum(chunks), seed=1)
    cache, done = WorldModelCache(), 0
    with torch.no_grad():
        full = model(tokens, disp, cmd)
        for n in chunks:  # the KV cache grows past its first capacity here
            done += n
            out = model(tokens[:, :done], disp[:, : done - 1], cmd, cache=cache, last_only=True)
            for lf, ll in zip(full.logits, out.logits):
                torch.testing.assert_close(ll[:, 0], lf[:, done - 1], rtol=1e-4, atol=1e-5)
            torch.testing.assert_close(
                out.displacement, full.displacement[:, done - n : done], rtol=1e-4, atol=1e-5
            )
    assert cache.frames == done


def test_rollout_equals_the_recomputing_reference():
    model, tokens, disp, cmd = model_and_inputs(seed=2)
    fast = model.rollout(tokens, disp, cmd, steps=6)
    ref = model.rollout(tokens, disp, cmd, steps=6, use_cache=False)
    torch.testing.assert_close(fast.tokens, ref.tokens, rtol=0, atol=0)
    torch.testing.assert_close(fast.trajectory, ref.trajectory, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("use_cache", [True, False])
def test_trajectory_only_rollout_skips_codes_not_displacements(use_cache):
    model, tokens, disp, cmd = model_and_inputs(seed=3)
    calls = []
    model.code_heads[0].register_forward_hook(lambda *_: calls.append(1))
    full = model.rollout(tokens, disp, cmd, steps=6, use_cache=use_cache)
    n_full, calls[:] = len(calls), []
    fast = model.rollout(tokens, disp, cmd, steps=6, use_cache=use_cache, trajectory_only=True)
    assert fast.tokens is None and len(calls) == n_full - 1  # the last step's heads skipped
    assert torch.equal(fast.displacements, full.displacements)
    assert torch.equal(fast.trajectory, full.trajectory)
    with torch.no_grad():
        a = model(tokens, disp, cmd)
        b = model(tokens, disp, cmd, with_logits=False)
    assert b.logits == [] and torch.equal(a.displacement, b.displacement)


def test_rollout_checks_its_history_once():
    model, tokens, disp, cmd = model_and_inputs()
    with pytest.raises(ValueError, match=r"tokens: codebook 0 codes must lie in \[0, 8\)"):
        model.rollout(tokens + 100, disp, cmd, steps=2)
    with pytest.raises(ValueError, match="displacements: expected finite values"):
        model.rollout(tokens, disp * float("nan"), cmd, steps=2)
