import pytest
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer import VARIANTS, TokenizerConfig, Tokens, build_tokenizer

from .synthetic import street_batch

GRID = (32, 32, 8)


def tiny(variant: str, **kw) -> TokenizerConfig:
    base = dict(
        variant=variant,
        grid_shape=GRID,
        latent_shape=(8, 8),
        latent_channels=8,
        codebook_size=16,
        embed_dim=2,
        base_channels=8,
        num_res_blocks=1,
    )
    base.update(kw)
    return TokenizerConfig(**base)


@pytest.fixture(scope="module")
def occ():
    return street_batch(2, GRID)


@pytest.mark.parametrize("variant", VARIANTS)
def test_shapes_dtypes_and_round_trip(variant, occ):
    torch.manual_seed(0)
    model = build_tokenizer(tiny(variant))
    g = model.cfg.num_codebooks
    out = model(occ)
    assert out.logits.shape == (2, *GRID, NUM_OCC3D_CLASSES) and out.logits.dtype == torch.float32
    assert out.loss.dim() == 0 and torch.isfinite(out.loss)
    assert out.tokens.indices.shape == (2, g, 8, 8) and out.tokens.indices.dtype == torch.int64
    assert out.tokens.codebook_sizes == model.cfg.codebook_sizes
    expected_names = ("air", "non_air") if g == 2 else ("scene",)
    assert out.tokens.codebook_names == expected_names
    keys = {"loss/total", "loss/recon", "loss/ce", "loss/lovasz", "loss/commit"}
    if model.cfg.air_mask_head:
        keys |= {"loss/air", "loss/non_air"}
        # log-probabilities of a proper 18-way distribution
        assert torch.allclose(out.logits.logsumexp(-1), torch.zeros(()), atol=1e-5)
    for name in expected_names:
        keys |= {f"codebook/{name}/{s}" for s in ("usage", "perplexity", "window_usage")}
    assert keys <= set(out.logs) and all(v.dim() == 0 for v in out.logs.values())
    out.loss.backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(gr is not None and torch.isfinite(gr).all() for gr in grads)

    model.eval()
    with torch.no_grad():
        ref = model(occ, compute_loss=False)
        tokens = model.encode(occ)
        assert torch.equal(tokens.indices, ref.tokens.indices)
        rec = model.decode(tokens)
        assert rec.shape == occ.shape and rec.dtype == torch.uint8
        assert torch.equal(rec, model.predict(ref.logits))
        assert torch.equal(model.decode_logits(tokens), ref.logits)
        if not model.cfg.air_mask_head:
            assert torch.equal(rec, ref.logits.argmax(-1).to(torch.uint8))
        # a [B, T, G, h, w] sequence decodes frame by frame
        seq = Tokens(tokens.indices[:, None].repeat(1, 3, 1, 1, 1), *_meta(tokens))
        dec = model.decode(seq)
        assert dec.shape == (2, 3, *GRID) and torch.equal(dec[:, 1], rec)


def _meta(tokens):
    return tokens.codebook_sizes, tokens.codebook_names


def test_encode_never_updates_the_codebook(occ):
    model = build_tokenizer(tiny("am_vae"))
    model(occ)  # first training forward initialises the codebooks
    state = {k: v.clone() for k, v in model.state_dict().items()}
    model.train()
    model.encode(occ)
    assert all(torch.equal(state[k], v) for k, v in model.state_dict().items())


@pytest.mark.parametrize(
    "grid, latent",
    [("coarse", (25, 25)), ("coarse", (50, 50)), ("quarter", (25, 25)), ("occ3d", (50, 50))],
)
def test_named_grids(grid, latent):
    cfg = TokenizerConfig.for_grid(
        grid,
        latent_shape=latent,
        latent_channels=4,
        codebook_size=8,
        embed_dim=1,
        base_channels=4,
        num_res_blocks=0,
        attention=grid != "occ3d",
    )
    model = build_tokenizer(cfg).eval()
    occ = torch.full((1, *cfg.grid_shape), FREE_ID, dtype=torch.uint8)
    occ[..., 0] = 11
    with torch.no_grad():
        tokens = model.encode(occ)
        assert tokens.grid_shape == latent
        assert model.decode(tokens).shape == occ.shape


def test_all_free_volume_trains_finite():
    model = build_tokenizer(tiny("am_vae", dead_code_steps=1))
    occ = torch.full((2, *GRID), FREE_ID, dtype=torch.int64)
    for _ in range(3):
        out = model(occ)
        out.loss.backward()
        assert torch.isfinite(out.loss)
        assert float(out.losses["non_air"]) == 0.0
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_bad_inputs(occ):
    model = build_tokenizer(tiny("plain"))
    with pytest.raises(TypeError, match="occ: expected an integer tensor"):
        model(occ.float())
    with pytest.raises(TypeError, match="occ: expected a torch.Tensor"):
        model(occ.numpy())
    with pytest.raises(ValueError, match=r"occ: expected shape \[B, \(32, 32, 8\)\]"):
        model(occ[:, :16])
    with pytest.raises(ValueError, match=r"occ: expected shape"):
        model(occ[0])
    bad = occ.clone()
    bad[0, 0, 0, 0] = NUM_OCC3D_CLASSES
    with pytest.raises(ValueError, match=r"occ: expected Occ3D class ids in \[0, 17\], got range"):
        model.encode(bad)
    tokens = model.encode(occ)
    with pytest.raises(TypeError, match="tokens: expected Tokens"):
        model.decode(tokens.indices)
    other = Tokens(tokens.indices.repeat(1, 2, 1, 1), (8, 8), ("air", "non_air"))
    with pytest.raises(ValueError, match="tokens: expected codebooks"):
        model.decode(other)
    with pytest.raises(ValueError, match=r"tokens: expected a latent grid \(8, 8\)"):
        model.decode(Tokens(tokens.indices[..., :4], *_meta(tokens)))
    with pytest.raises(ValueError, match="tokens: indices outside"):
        model.decode(Tokens(tokens.indices + 16, *_meta(tokens)))
