import pytest
import torch

from renderworld.constants import COMMANDS
from renderworld.world import WorldModel, WorldModelConfig, world_model_loss
from renderworld.world.loss import WorldModelTargets

TINY = dict(
    codebook_sizes=(5, 18),
    token_grid=(8, 8),
    embed_dim=16,
    num_heads=2,
    num_scales=3,
    layers_per_scale=(1, 1, 1),
)


def tiny_model(seed=0, **kw):
    torch.manual_seed(seed)
    return WorldModel(WorldModelConfig(**{**TINY, **kw})).eval()


def random_inputs(b=2, t=5, seed=1, cfg=None):
    cfg = cfg or WorldModelConfig(**TINY)
    g = torch.Generator().manual_seed(seed)
    tokens = torch.stack(
        [torch.randint(0, k, (b, t, *cfg.token_grid), generator=g) for k in cfg.codebook_sizes],
        dim=2,
    )
    disp = torch.randn(b, t - 1, 2, generator=g) * 3
    cmd = torch.randint(0, len(COMMANDS), (b,), generator=g)
    return tokens, disp, cmd


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(embed_dim=15), "embed_dim"),
        (dict(layers_per_scale=(1, 1)), "layers_per_scale"),
        (dict(codebook_sizes=()), "codebook_sizes"),
        (dict(codebook_sizes=(1,)), "codebook_sizes"),
        (dict(token_grid=(2, 2)), "num_scales"),
        (dict(max_displacement=0.0), "max_displacement"),
        (dict(num_scales=0, layers_per_scale=()), "num_scales"),
    ],
)
def test_config_validation(kw, match):
    with pytest.raises(ValueError, match=match):
        WorldModelConfig(**{**TINY, **kw})


def test_config_dict_round_trip():
    cfg = WorldModelConfig(**TINY)
    assert WorldModelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown WorldModelConfig keys"):
        WorldModelConfig.from_dict({**cfg.to_dict(), "bogus": 1})


@pytest.mark.parametrize("grid", [(8, 8), (10, 7)])
def test_forward_shapes(grid):
    m = tiny_model(token_grid=grid)
    tokens, disp, cmd = random_inputs(cfg=m.config)
    out = m(tokens, disp, cmd)
    assert [tuple(lg.shape) for lg in out.logits] == [(2, 5, 5, *grid), (2, 5, 18, *grid)]
    assert out.displacement.shape == (2, 5, 2)
    assert out.displacement_modes.shape == (2, 5, len(COMMANDS), 2)


def test_input_validation():
    m = tiny_model()
    tokens, disp, cmd = random_inputs()
    bad = tokens.clone()
    bad[0, 0, 0, 0, 0] = 5
    with pytest.raises(ValueError, match=r"tokens: codebook 0 codes must lie in \[0, 5\)"):
        m(bad, disp, cmd)
    with pytest.raises(ValueError, match=r"displacements: expected \[B, T-1, 2\]"):
        m(tokens, disp[:, :-1], cmd)
    with pytest.raises(ValueError, match="displacements: expected finite"):
        m(tokens, disp * float("nan"), cmd)
    with pytest.raises(ValueError, match="command: expected indices"):
        m(tokens, disp, torch.tensor([0, 3]))
    with pytest.raises(TypeError, match="tokens: expected an int64"):
        m(tokens.int(), disp, cmd)
    long_tokens, long_disp, _ = random_inputs(t=m.config.max_frames + 1)
    with pytest.raises(ValueError, match="tokens: expected 1..10 frames"):
        m(long_tokens, long_disp, cmd)


def test_causal_future_frame_does_not_change_earlier_predictions():
    m = tiny_model()
    tokens, disp, cmd = random_inputs(t=7)
    base = m(tokens, disp, cmd)
    j = 4
    changed = tokens.clone()
    changed[:, j:] = (changed[:, j:] + 1) % 5  # valid in both codebooks (sizes 5 and 18)
    disp2 = disp.clone()
    disp2[:, j - 1 :] += 2.0  # displacement into frame j and later
    out = m(changed, disp2, cmd)
    for a, b in zip(base.logits, out.logits):
        torch.testing.assert_close(a[:, :j], b[:, :j], rtol=0, atol=1e-6)
        assert not torch.allclose(a[:, j:], b[:, j:])
    torch.testing.assert_close(base.displacement[:, :j], out.displacement[:, :j], rtol=0, atol=1e-6)
    assert not torch.allclose(base.displacement[:, j:], out.displacement[:, j:])


def test_untrained_cv_residual_model_plans_constant_velocity():
    m = tiny_model()
    tokens, disp, cmd = random_inputs()
    out = m(tokens, disp, cmd)
    # Prediction i is d[i]; its prior is d[i-1] (zero for frame 0), bounded by tanh.
    prior = torch.cat([torch.zeros_like(disp[:, :1]), disp], dim=1)
    bound = m.config.max_displacement
    expected = bound * torch.tanh(prior / bound)
    torch.testing.assert_close(out.displacement, expected, rtol=0, atol=1e-6)


def test_command_selects_ego_mode():
    m = tiny_model()
    torch.nn.init.normal_(m.ego_head.weight)  # a trained head: the modes differ
    tokens, disp, _ = random_inputs()
    outs = []
    for c in range(len(COMMANDS)):
        cmd = torch.full((2,), c)
        out = m(tokens, disp, cmd)
        torch.testing.assert_close(out.displacement, out.displacement_modes[:, :, c])
        outs.append(out.displacement)
    assert not torch.allclose(outs[0], outs[1])


def test_gradients_finite_on_hard_inputs():
    cfg = WorldModelConfig(**TINY)
    m = WorldModel(cfg).train()
    b, t = 2, cfg.max_frames
    tokens = torch.zeros(b, t, 2, 8, 8, dtype=torch.long)
    tokens[:, :, 1] = 17  # all-free scene, identical frames
    disp = torch.full((b, t - 1, 2), cfg.max_displacement)  # maximum speed
    out = m(tokens, disp, torch.tensor([0, 2]))
    tgt = WorldModelTargets(tokens, torch.full((b, t, 2), 1e4))  # target far beyond the bound
    loss = world_model_loss(out, tgt, lambda_l2=0.1)["loss"]
    loss.backward()
    assert torch.isfinite(loss)
    for name, p in m.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert out.displacement.abs().max() <= cfg.max_displacement


def test_float32_matches_float64_reference():
    m32 = tiny_model()
    m64 = tiny_model().double()
    tokens, disp, cmd = random_inputs(t=6)
    a = m32(tokens, disp, cmd)
    b = m64(tokens, disp.double(), cmd)
    for x, y in zip(a.logits, b.logits):
        torch.testing.assert_close(x.double(), y, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(a.displacement.double(), b.displacement, rtol=1e-4, atol=1e-4)
