import pytest
import torch

from renderworld.constants import COMMANDS, FREE_ID
from renderworld.world import WorldModel, rollout
from renderworld.world.model import WorldModelCache
from tests.world.test_model import TINY, random_inputs, tiny_model


def test_rollout_shapes_and_trajectory_is_cumsum():
    m = tiny_model()
    tokens, disp, cmd = random_inputs()
    out = m.rollout(tokens, disp, cmd)
    assert out.tokens.shape == (2, 6, 2, 8, 8) and out.tokens.dtype == torch.int64
    assert out.displacements.shape == (2, 6, 2)
    torch.testing.assert_close(out.trajectory, out.displacements.cumsum(1))
    # The first step is exactly the teacher-forced prediction of the last history position.
    first = m(tokens, disp, cmd)
    torch.testing.assert_close(out.tokens[:, 0, 0], first.logits[0][:, -1].argmax(1))
    torch.testing.assert_close(out.tokens[:, 0, 1], first.logits[1][:, -1].argmax(1))
    torch.testing.assert_close(out.displacements[:, 0], first.displacement[:, -1])


def test_rollout_feeds_back_own_predictions_and_holds_command(monkeypatch):
    m = tiny_model()
    tokens, disp, cmd = random_inputs()
    calls = []
    original = WorldModel.forward

    def spy(self, tok, d, c, cache=None, **kwargs):
        calls.append((tok.clone(), d.clone(), c.clone()))
        return original(self, tok, d, c, cache=cache, **kwargs)

    monkeypatch.setattr(WorldModel, "forward", spy)
    out = rollout(m, tokens, disp, cmd, steps=6)
    assert len(calls) == 6
    for k, (tok, d, c) in enumerate(calls):
        assert torch.equal(c, cmd)  # the current command at every step, never another one
        assert tok.shape[1] == 5 + k and d.shape[1] == 4 + k
        assert torch.equal(tok[:, :5], tokens) and torch.equal(d[:, :4], disp)
        if k:
            assert torch.equal(tok[:, 5:], out.tokens[:, :k])  # its own argmax codes
            assert torch.equal(d[:, 4:], out.displacements[:, :k])


@pytest.mark.parametrize("steps", [6, 9])  # 9 > window: the cached path falls back
def test_cached_rollout_matches_recompute_reference(steps):
    m = tiny_model()
    tokens, disp, cmd = random_inputs()
    fast = m.rollout(tokens, disp, cmd, steps=steps, use_cache=True)
    ref = m.rollout(tokens, disp, cmd, steps=steps, use_cache=False)
    assert torch.equal(fast.tokens, ref.tokens)
    torch.testing.assert_close(fast.displacements, ref.displacements, rtol=1e-5, atol=1e-5)


def test_forward_in_pieces_with_cache_equals_whole():
    m = tiny_model()
    tokens, disp, cmd = random_inputs(t=8)
    whole = m(tokens, disp, cmd)
    cache = WorldModelCache()
    parts = [m(tokens[:, :n], disp[:, : n - 1], cmd, cache=cache) for n in (3, 4, 8)]
    assert cache.frames == 8
    for g in range(2):
        got = torch.cat([p.logits[g] for p in parts], dim=1)
        torch.testing.assert_close(got, whole.logits[g], rtol=1e-4, atol=1e-5)
    got = torch.cat([p.displacement for p in parts], dim=1)
    torch.testing.assert_close(got, whole.displacement, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="cache: expected a WorldModelCache holding fewer than 8"):
        m(tokens, disp, cmd, cache=cache)


def test_rollout_command_changes_selected_head_only():
    m = tiny_model()
    torch.nn.init.normal_(m.ego_head.weight)  # a trained head: the command modes differ
    tokens, disp, _ = random_inputs()
    left = m.rollout(tokens, disp, torch.full((2,), COMMANDS.index("left")))
    right = m.rollout(tokens, disp, torch.full((2,), COMMANDS.index("right")))
    assert not torch.allclose(left.displacements[:, 0], right.displacements[:, 0])
    modes = m(tokens, disp, torch.full((2,), COMMANDS.index("left"))).displacement_modes
    torch.testing.assert_close(left.displacements[:, 0], modes[:, -1, COMMANDS.index("left")])


@pytest.mark.parametrize("case", ["all_free", "identical", "max_speed", "reverse_max"])
def test_rollout_hard_histories_stay_finite_and_in_range(case):
    m = tiny_model()
    cfg = m.config
    tokens, disp, cmd = random_inputs()
    if case == "all_free":
        tokens = torch.zeros_like(tokens)
        tokens[:, :, 1] = FREE_ID
        disp = torch.zeros_like(disp)
    elif case == "identical":
        tokens = tokens[:, :1].expand_as(tokens).clone()
    elif case == "max_speed":
        disp = torch.full_like(disp, cfg.max_displacement)
    else:
        disp = torch.full_like(disp, -cfg.max_displacement)
    out = m.rollout(tokens, disp, cmd, steps=12)  # longer than the window: context slides
    for g, k in enumerate(cfg.codebook_sizes):
        assert out.tokens[:, :, g].min() >= 0 and out.tokens[:, :, g].max() < k
    assert torch.isfinite(out.displacements).all()
    assert out.displacements.abs().max() <= cfg.max_displacement
    assert out.trajectory.abs().max() <= 12 * cfg.max_displacement


def test_rollout_validation():
    m = tiny_model()
    tokens, disp, cmd = random_inputs()
    with pytest.raises(ValueError, match="steps: expected an int >= 1"):
        rollout(m, tokens, disp, cmd, steps=0)
    with pytest.raises(ValueError, match="history_tokens: expected"):
        rollout(m, tokens[0], disp, cmd)


@pytest.mark.parametrize("t, total", [(5, 5), (2, 5), (4, 11), (10, 10)])
def test_short_causal_attention_matches_the_fused_reference(t, total):
    from renderworld.world.blocks import causal_attention_reference, short_causal_attention

    g = torch.Generator().manual_seed(t * 100 + total)
    q = torch.randn(300, 2, t, 8, generator=g)
    k, v = torch.randn(2, 300, 2, total, 8, generator=g).unbind(0)
    ref = causal_attention_reference(q, k, v)
    torch.testing.assert_close(short_causal_attention(q, k, v), ref, rtol=1e-5, atol=1e-6)
    # Scores of ~1e4 (one key dominates each row) stay finite and agree with the fused kernel
    # to the rounding of such scores in float32 (~1e-3 of a weight).
    big = short_causal_attention(q * 300.0, k * 300.0, v)
    assert torch.isfinite(big).all()
    ref_big = causal_attention_reference(q * 300.0, k * 300.0, v)
    torch.testing.assert_close(big, ref_big, rtol=0, atol=1e-2)
    # The first query of a prefix sees only the first key: its output is that key's value.
    if t == total:
        torch.testing.assert_close(short_causal_attention(q, k, v)[:, :, 0], v[:, :, 0])


def test_inference_attention_equals_the_training_path(monkeypatch):
    """The rollout's prefix runs the explicit products without autograd, training the fused
    kernel: a teacher-forced window gives the same predictions either way."""
    from renderworld.world import blocks

    calls = []
    short = blocks.short_causal_attention
    monkeypatch.setattr(
        blocks, "short_causal_attention", lambda *a: calls.append(a[0].shape) or short(*a)
    )
    m = tiny_model()
    tokens, disp, cmd = random_inputs(t=6)
    with torch.no_grad():
        fast = m(tokens, disp, cmd)
    taken = len(calls)
    with torch.enable_grad():
        fused = m(tokens, disp, cmd)
    # Every scene block of every scale and the ego block took the products, training none.
    assert taken == sum(TINY["layers_per_scale"]) + 1 and len(calls) == taken
    for a, b in zip(fast.logits, fused.logits):
        torch.testing.assert_close(a, b.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fast.displacement, fused.displacement.detach(), rtol=1e-5, atol=1e-5)
