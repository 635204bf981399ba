"""The fast paths against their references: codec vs SceneTokenizer, fast vs reference planner,
trajectory-only vs full plans, streaming session vs re-planning, bf16 vs float32."""

import re
import warnings

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID
from renderworld.planning import Planner, PlannerSession, PlanRequest
from renderworld.precision import exact_float32
from renderworld.tokenizer import VARIANTS, TokenizerConfig, build_tokenizer
from renderworld.tokenizer.inference import FastSceneCodec
from renderworld.tokenizer.tokens import Tokens
from renderworld.world import WorldModel, WorldModelConfig

GRID = (32, 32, 4)
# 3 resolution levels (two up-samplings), attention at the latent: every fast kernel runs.
TOK = TokenizerConfig(
    grid_shape=GRID, latent_shape=(8, 8), latent_channels=8, codebook_size=32,
    base_channels=8, num_res_blocks=1, attention=True,
)  # fmt: skip


def scene_planner(seed=0, variant="am_vae", **options):
    torch.manual_seed(seed)
    tok = build_tokenizer(TOK.replace(variant=variant))
    cfg = WorldModelConfig(
        codebook_sizes=tuple(tok.cfg.codebook_sizes), token_grid=tok.cfg.latent_shape,
        embed_dim=16, num_heads=2, num_scales=2, layers_per_scale=(1, 1),
    )  # fmt: skip
    wm = WorldModel(cfg)
    torch.nn.init.normal_(wm.ego_head.weight, std=0.5)  # trained-like: the ego head matters
    return Planner(tok, wm, **options)


def street(t, seed=0):
    """A street-like sequence: road at z=0, objects at z=1 moving with the frames."""
    rng = np.random.default_rng(seed)
    occ = np.full((t, *GRID), FREE_ID, dtype=np.uint8)
    occ[..., 0] = 11
    xs, ys = rng.integers(0, GRID[0], 40), rng.integers(0, GRID[1], 40)
    for i in range(t):
        occ[i, (xs + i) % GRID[0], ys, 1] = rng.integers(1, 17, 40)
    disp = np.column_stack([rng.uniform(2, 6, t - 1), rng.uniform(-0.4, 0.4, t - 1)])
    return occ, disp


@pytest.mark.parametrize("variant", VARIANTS)
def test_codec_matches_the_tokenizer(variant):
    torch.manual_seed(1)
    tok = build_tokenizer(TOK.replace(variant=variant)).eval()
    codec = FastSceneCodec(tok)
    occ = torch.from_numpy(street(4)[0])
    with torch.inference_mode():
        ref_tokens, fast_tokens = tok.encode(occ), codec.encode(occ)
        assert fast_tokens.codebook_sizes == ref_tokens.codebook_sizes
        torch.testing.assert_close(fast_tokens.indices, ref_tokens.indices, rtol=0, atol=0)
        g = torch.Generator().manual_seed(2)
        idx = torch.stack(
            [torch.randint(0, k, (2, 3, 8, 8), generator=g) for k in tok.cfg.codebook_sizes], 2
        )  # [2, 3, G, h, w]: leading dims are kept
        tokens = Tokens(idx, tok.cfg.codebook_sizes, tok.cfg.codebook_names)
        ref, fast = tok.decode(tokens), codec.decode(tokens)
    assert fast.shape == ref.shape == (2, 3, *GRID) and fast.dtype == torch.uint8
    # Same decisions up to rounding: at most 0.1 % of voxels may flip (ties within ~1e-6).
    assert (fast == ref).float().mean().item() >= 0.999


def test_codec_follows_new_weights_and_refuses_bad_input():
    tok = build_tokenizer(TOK).eval()
    codec = FastSceneCodec(tok)
    occ = torch.from_numpy(street(2)[0])
    with torch.inference_mode():
        before = codec.encode(occ).indices.clone()
        tok.quantizers[0].codebook.copy_(torch.roll(tok.quantizers[0].codebook, 1, 0))
        torch.testing.assert_close(codec.encode(occ).indices, tok.encode(occ).indices)
        assert not torch.equal(codec.encode(occ).indices, before)
        g = torch.Generator().manual_seed(3)
        idx = torch.stack([torch.randint(0, k, (2, 8, 8), generator=g) for k in (16, 16)], 1)
        tokens = Tokens(idx, tok.cfg.codebook_sizes, tok.cfg.codebook_names)
        first = codec.decode(tokens)
        for conv in (tok.decoder.conv_in, tok.decoder.blocks[-2].conv):  # 3x3 and up-sampling
            conv.weight.mul_(-3.0)  # in place: cached re-packed weights must notice
        second = codec.decode(tokens)
        assert (second == tok.decode(tokens)).float().mean().item() >= 0.999
        assert (second != first).any()
    with pytest.raises(TypeError, match="tokenizer: expected SceneTokenizer"):
        FastSceneCodec(torch.nn.Linear(1, 1))
    with pytest.raises(ValueError, match=r"occ: expected shape \[B, \(32, 32, 4\)\]"):
        codec.encode(occ[:, :8])
    with pytest.raises(TypeError, match="tokens: expected Tokens"):
        codec.decode(occ)


def test_codec_in_passes_equals_one_frame_at_a_time():
    """``max_batch`` bounds the frames per trunk pass (a CPU planner runs one at a time): a
    frame's tokens and voxels are those of coding it alone, in the input's order."""
    torch.manual_seed(4)
    tok = build_tokenizer(TOK).eval()
    occ = torch.from_numpy(street(5)[0])
    g = torch.Generator().manual_seed(5)
    idx = torch.stack([torch.randint(0, k, (5, 8, 8), generator=g) for k in (16, 16)], 1)
    tokens = Tokens(idx, tok.cfg.codebook_sizes, tok.cfg.codebook_names)
    single = FastSceneCodec(tok)
    with torch.inference_mode():
        alone = torch.cat([single.encode(occ[i : i + 1]).indices for i in range(5)])
        meta = tok.cfg.codebook_sizes, tok.cfg.codebook_names
        voxels = torch.cat([single.decode(Tokens(idx[i : i + 1], *meta)) for i in range(5)])
        for max_batch in (1, 2):
            codec = FastSceneCodec(tok, max_batch=max_batch)
            enc, dec = codec.encode(occ), codec.decode(tokens)
            assert enc.indices.shape == (5, 2, 8, 8) and dec.shape == (5, *GRID)
            if max_batch == 1:
                assert torch.equal(enc.indices, alone) and torch.equal(dec, voxels)
            assert (dec == tok.decode(tokens)).float().mean().item() >= 0.999
            torch.testing.assert_close(enc.indices, tok.encode(occ).indices, rtol=0, atol=0)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="max_batch: expected None or an int >= 1"):
            FastSceneCodec(tok, max_batch=bad)


def test_cpu_passes_hold_what_the_cache_holds():
    from renderworld.tokenizer.inference import cache_frames_per_pass

    paper = build_tokenizer(TokenizerConfig(latent_channels=8, codebook_size=16))  # 200x200, C0 64
    assert cache_frames_per_pass(paper) == 1  # 10 MB of full-resolution features a frame
    mini = build_tokenizer(
        TokenizerConfig(grid_shape=(50, 50, 4), latent_shape=(25, 25), base_channels=32)
    )
    assert cache_frames_per_pass(mini) == 52  # 0.3 MB a frame: a whole plan in one pass
    assert cache_frames_per_pass(mini, budget=1) == 1
    # A CPU planner's codec runs passes of that size; an empty batch still decodes.
    planner = scene_planner()
    codec = planner._encode_fn.__self__
    assert codec.max_batch == cache_frames_per_pass(planner.tokenizer)
    cfg = planner.tokenizer.cfg
    empty = Tokens(
        torch.zeros(0, 2, 8, 8, dtype=torch.long), cfg.codebook_sizes, cfg.codebook_names
    )
    assert FastSceneCodec(planner.tokenizer, max_batch=1).decode(empty).shape == (0, *GRID)


def test_fast_planner_matches_the_reference_planner():
    fast, ref = scene_planner(fast=True), scene_planner(fast=False)
    for seed, command in ((0, "straight"), (1, "left"), (2, "right")):
        occ, disp = street(6, seed)
        req = PlanRequest(occ, disp, command)
        a, b = fast.plan(req), ref.plan(req)
        np.testing.assert_allclose(a.trajectory, b.trajectory, atol=1e-4)
        assert (a.occupancy_forecast == b.occupancy_forecast).mean() >= 0.999


class CountingTokenizer(torch.nn.Module):
    """Wraps a tokenizer and counts encoded frames and decode calls."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner
        self.encoded = self.decodes = 0

    def encode(self, occ):
        self.encoded += occ.shape[0]
        return self.inner.encode(occ)

    def decode(self, tokens):
        self.decodes += 1
        return self.inner.decode(tokens)


def test_trajectory_only_skips_the_decode_and_keeps_the_trajectory():
    planner = scene_planner()
    counting = CountingTokenizer(planner.tokenizer)
    planner = Planner(counting, planner.world_model)
    occ, disp = street(5, 3)
    req = PlanRequest(occ, disp, "left")
    full = planner.plan(req)
    assert counting.decodes == 1
    traj_only = planner.plan(req, forecast=False)
    assert counting.decodes == 1  # no occupancy decode at all
    assert traj_only.occupancy_forecast is None and traj_only.timings["decode"] < 1.0
    np.testing.assert_array_equal(traj_only.trajectory, full.trajectory)
    batch = planner.plan_batch([req, PlanRequest(occ, disp, "right")], forecast=False)
    np.testing.assert_allclose(batch[0].trajectory, full.trajectory, atol=1e-5)  # batch rounding
    assert counting.decodes == 1


@pytest.mark.parametrize("fast", [True, False])
def test_session_equals_replanning_from_scratch(fast):
    planner = scene_planner(fast=fast)
    counting = CountingTokenizer(planner.tokenizer)
    streaming = Planner(counting, planner.world_model, fast=fast)
    session = PlannerSession(streaming)
    occ, disp = street(9, 4)  # 9 frames: the 5-frame window slides 4 times
    plans = 0
    for t in range(len(occ)):
        d = disp[:t]  # in a real loop re-expressed in the current frame; any valid rows work
        result = session.step(occ[t], d, "straight" if t % 2 else "left", forecast=t % 3 > 0)
        assert counting.encoded == t + 1  # one encode per new frame
        if t < 4:
            assert result is None and not session.ready
            continue
        plans += 1
        ref = planner.plan(PlanRequest(occ[: t + 1], d, "straight" if t % 2 else "left"))
        np.testing.assert_allclose(result.trajectory, ref.trajectory, atol=1e-5)
        if t % 3 > 0:
            np.testing.assert_array_equal(result.occupancy_forecast, ref.occupancy_forecast)
        else:
            assert result.occupancy_forecast is None
    assert plans == 5 and session.frames_seen == 9
    again = session.plan(disp[:8], "left")  # planning twice costs no encode
    assert counting.encoded == 9 and again.timings["encode"] == 0.0
    session.reset()
    assert not session.ready


def test_bfloat16_keeps_the_trajectory_and_bounds_the_forecast_change():
    for seed in range(2):
        f32, bf16 = scene_planner(seed), scene_planner(seed, precision="bfloat16")
        for case in range(2):
            occ, disp = street(5, case)
            req = PlanRequest(occ, disp, "straight")
            a, b = f32.plan(req), bf16.plan(req)
            assert b.trajectory.dtype == np.float32 and b.occupancy_forecast.dtype == np.uint8
            np.testing.assert_array_equal(a.trajectory, b.trajectory)  # world model in fp32
            agree = (a.occupancy_forecast == b.occupancy_forecast).mean()
            assert agree >= 0.98, agree  # untrained decoder: many near-tie voxels


@pytest.mark.slow
def test_compiled_decoder_matches_eager():
    eager, compiled = scene_planner(), scene_planner(compile="default")
    occ, disp = street(5, 5)
    req = PlanRequest(occ, disp, "left")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a silent fallback to eager would pass unnoticed
        a, b = eager.plan(req), compiled.plan(req)
    np.testing.assert_array_equal(a.trajectory, b.trajectory)
    assert (a.occupancy_forecast == b.occupancy_forecast).mean() >= 0.999


def test_compile_failure_falls_back_to_eager(monkeypatch):
    """A real compilation failure (no working C++ compiler): warn once, then run eagerly."""
    import torch._inductor.config as inductor_config

    monkeypatch.setattr(inductor_config.cpp, "cxx", ("/nonexistent/c++",))
    monkeypatch.setattr(inductor_config, "fx_graph_cache", False)  # no cached kernel to reuse
    torch._dynamo.reset()
    planner, eager = scene_planner(compile="default"), scene_planner()
    occ, disp = street(5, 7)
    req = PlanRequest(occ, disp, "left")
    with pytest.warns(RuntimeWarning, match="compile='default': torch.compile failed .*C\\+\\+"):
        a = planner.plan(req)
    np.testing.assert_array_equal(a.occupancy_forecast, eager.plan(req).occupancy_forecast)
    assert planner._compiled is None  # warned once, eager from then on
    torch._dynamo.reset()


@pytest.mark.parametrize(
    "error",
    [
        torch.OutOfMemoryError("CUDA out of memory"),
        RuntimeError("shapes cannot be multiplied"),
        torch._dynamo.exc.BackendCompilerFailed(
            torch.compile, torch.OutOfMemoryError("CUDA out of memory while autotuning"), None
        ),
    ],
    ids=["out_of_memory", "shape_bug", "out_of_memory_while_compiling"],
)
def test_other_errors_of_the_compiled_decoder_are_raised(error):
    """Out of memory or a shape bug is the caller's to see: no silent switch to eager mode."""
    planner = scene_planner()

    def failing(tokens):
        raise error

    planner._compiled, planner.compile = failing, "default"
    req = PlanRequest(*street(5, 7), "left")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(type(error), match=re.escape(str(error))):
            planner.plan(req)
    assert planner._compiled is failing  # still compiled: the next call tries it again


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.mark.gpu
@needs_cuda
@pytest.mark.parametrize("options", [{}, {"precision": "bfloat16"}, {"compile": "reduce-overhead"}])
def test_cuda_plans_match_cpu(options):
    cpu = scene_planner()
    gpu = scene_planner(device="cuda", **options)
    assert gpu.pin_memory
    occ, disp = street(5, 6)
    req = PlanRequest(occ, disp, "right")
    # Precision settings (TF32) are a caller's speed choice and earlier tests may leave them on:
    # compare in exact float32, as the export does (on an H200 alone: 3.5 mm with TF32, 1e-5 m off).
    with exact_float32():
        a, b = cpu.plan(req), gpu.plan(req)
    tol = 0.25 if options.get("precision") == "bfloat16" else 1e-3
    np.testing.assert_allclose(a.trajectory, b.trajectory, atol=tol)
    assert (a.occupancy_forecast == b.occupancy_forecast).mean() >= 0.99
