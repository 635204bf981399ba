import numpy as np
import pytest
import torch

from renderworld.constants import COMMANDS, FREE_ID
from renderworld.planning import Planner, PlanRequest, PlanResult
from renderworld.tokenizer.tokens import Tokens
from renderworld.world import WorldModel, WorldModelConfig
from tests.world.fake_tokenizer import PatchTokenizer, PatchTokenizerConfig

GRID = (8, 8, 4)


def make_planner(seed=0, num_codebooks=2):
    torch.manual_seed(seed)
    tok = PatchTokenizer(PatchTokenizerConfig(GRID, patch=2, num_codebooks=num_codebooks))
    cfg = WorldModelConfig(
        codebook_sizes=tok.codebook_sizes, token_grid=tok.token_grid, embed_dim=16,
        num_heads=2, num_scales=2, layers_per_scale=(1, 1),
    )  # fmt: skip
    wm = WorldModel(cfg)
    # Trained-like: the ego head starts at zero (the constant-velocity prior whatever the tokens
    # or the command), so a plan that ignored either would pass every comparison below.
    torch.nn.init.normal_(wm.ego_head.weight, std=0.5)
    return Planner(tok, wm)


def make_request(t=5, seed=0, command="straight"):
    rng = np.random.default_rng(seed)
    occ = np.full((t, *GRID), FREE_ID, dtype=np.uint8)
    occ[:, :, :, 0] = 11
    occ[:, 4:6, 2:4, 1] = rng.integers(1, 11, size=(t, 2, 2))
    occ[:, 2:4, 4:6, 1:3] = rng.integers(1, 11, size=(t, 1, 1, 1))  # one object: a code per frame
    disp = np.column_stack([rng.uniform(1, 5, t - 1), rng.uniform(-0.3, 0.3, t - 1)])
    return PlanRequest(occ, disp, command)


def test_plan_result_shapes_and_types():
    planner = make_planner()
    res = planner.plan(make_request())
    assert isinstance(res, PlanResult)
    assert res.trajectory.shape == (6, 2) and res.trajectory.dtype == np.float32
    assert np.isfinite(res.trajectory).all()
    assert res.occupancy_forecast.shape == (6, *GRID) and res.occupancy_forecast.dtype == np.uint8
    assert res.occupancy_forecast.max() <= FREE_ID
    assert {"encode", "world_model", "decode", "total"} <= set(res.timings)
    assert res.timings["total"] >= res.timings["world_model"] >= 0


@pytest.mark.parametrize("num_codebooks", [1, 2])
@pytest.mark.parametrize("command", COMMANDS)
def test_plan_matches_tokenizer_and_world_model_directly(num_codebooks, command):
    planner = make_planner(num_codebooks=num_codebooks)
    req = make_request(command=command)
    res = planner.plan(req)
    tokens = planner.tokenizer.encode(torch.from_numpy(req.occupancy))
    out = planner.world_model.rollout(
        tokens.indices[None],
        torch.from_numpy(req.ego_displacements).float()[None],
        torch.tensor([COMMANDS.index(command)]),
    )
    np.testing.assert_allclose(res.trajectory, out.trajectory[0].numpy(), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(
        res.trajectory, np.cumsum(out.displacements[0].numpy(), 0), atol=1e-5
    )
    decoded = planner.tokenizer.decode(
        Tokens(out.tokens[0], tokens.codebook_sizes, tokens.codebook_names)
    )
    np.testing.assert_array_equal(res.occupancy_forecast, decoded.numpy())
    # The comparison can fail: another command, or other history tokens, plan otherwise.
    other = COMMANDS[(COMMANDS.index(command) + 1) % len(COMMANDS)]
    moved = PlanRequest(req.occupancy, req.ego_displacements, other)
    assert np.abs(planner.plan(moved).trajectory - res.trajectory).max() > 1e-3
    occ = req.occupancy.copy()
    occ[:, :4, :4, 1:3] = 4  # cars in four patches: other codes
    rescene = planner.plan(PlanRequest(occ, req.ego_displacements, command))
    assert np.abs(rescene.trajectory - res.trajectory).max() > 1e-3


def test_uses_last_five_frames_and_never_mutates_inputs():
    planner = make_planner()
    long_req = make_request(t=8, seed=3)
    occ_before = long_req.occupancy.copy()
    disp_before = long_req.ego_displacements.copy()
    res_long = planner.plan(long_req)
    np.testing.assert_array_equal(long_req.occupancy, occ_before)
    np.testing.assert_array_equal(long_req.ego_displacements, disp_before)
    short = PlanRequest(long_req.occupancy[-5:], long_req.ego_displacements[-4:], "straight")
    res_short = planner.plan(short)
    np.testing.assert_array_equal(res_long.trajectory, res_short.trajectory)
    np.testing.assert_array_equal(res_long.occupancy_forecast, res_short.occupancy_forecast)


def test_plan_batch_equals_single_plans():
    planner = make_planner()
    reqs = [make_request(seed=1), make_request(t=6, seed=2, command="right")]
    batch = planner.plan_batch(reqs)
    for req, res in zip(reqs, batch):
        single = planner.plan(req)
        np.testing.assert_allclose(res.trajectory, single.trajectory, atol=1e-5)
        np.testing.assert_array_equal(res.occupancy_forecast, single.occupancy_forecast)
        assert res.timings["batch_size"] == 2


def test_command_changes_the_plan():
    planner = make_planner()
    torch.nn.init.normal_(planner.world_model.ego_head.weight)  # trained: the modes differ
    base = make_request()
    plans = {
        c: planner.plan(PlanRequest(base.occupancy, base.ego_displacements, c)).trajectory
        for c in ("left", "right", "straight")
    }
    assert not np.allclose(plans["left"], plans["right"])


def _occ(t=5, dtype=np.uint8):
    return np.full((t, *GRID), FREE_ID, dtype=dtype)


D4 = np.zeros((4, 2))
VE = ValueError


@pytest.mark.parametrize(
    "occ, disp, command, exc, match",
    [
        (_occ(dtype=np.int64), D4, "left", VE, "occupancy: expected dtype uint8"),
        (_occ()[0], D4, "left", VE, r"occupancy: expected shape \[T, X, Y, Z\]"),
        (_occ(t=4), np.zeros((3, 2)), "left", VE, "occupancy: expected at least 5 history"),
        (_occ() + 1, D4, "left", VE, r"occupancy: expected class ids in \[0, 17\]"),
        (_occ(), D4.astype(np.int64), "left", VE, "ego_displacements: expected a float"),
        (_occ(), np.zeros((5, 2)), "left", VE, r"ego_displacements: expected shape \[T-1, 2\]"),
        (_occ(), np.full((4, 2), np.nan), "left", VE, "ego_displacements: expected finite"),
        (_occ(), D4, "up", VE, "command: expected one of"),
        (_occ(), D4, 0, VE, "command: expected one of"),
        ([[0]], D4, "left", TypeError, "occupancy: expected a numpy array"),
    ],
)
def test_request_validation(occ, disp, command, exc, match):
    with pytest.raises(exc, match=match):
        PlanRequest(occ, disp, command)


def test_planner_validation():
    planner = make_planner()
    with pytest.raises(ValueError, match="requests: expected at least one"):
        planner.plan_batch([])
    with pytest.raises(TypeError, match=r"requests\[0\]: expected PlanRequest"):
        planner.plan_batch([{"occupancy": 1}])
    other = PlanRequest(np.full((5, 4, 4, 4), FREE_ID, np.uint8), np.zeros((4, 2)), "left")
    with pytest.raises(ValueError, match=r"requests\[1\].occupancy: expected grid"):
        planner.plan_batch([make_request(), other])
    with pytest.raises(TypeError, match="tokenizer: expected an object with a callable .encode"):
        Planner(object(), planner.world_model)
    with pytest.raises(TypeError, match="world_model: expected WorldModel"):
        Planner(planner.tokenizer, torch.nn.Linear(1, 1))
    mismatched = Planner(PatchTokenizer(PatchTokenizerConfig(GRID, 2, 1)), planner.world_model)
    with pytest.raises(ValueError, match="tokenizer: codebook sizes"):
        mismatched.plan(make_request())
