"""The planner on a pose-warp world model (stage.forecaster=pose_warp): API, streaming, bundles.

The stage-level check (plan() equals the world_model stage's own evaluation forecast and
trajectory) is ``tests/training/test_world_model_pose.py``.
"""

import copy

import numpy as np
import pytest
import torch

from renderworld.constants import COMMANDS, FREE_ID, GridSpec
from renderworld.planning import (
    Planner,
    PlannerSession,
    PlanRequest,
    load_planner,
    register_tokenizer,
    save_planner_bundle,
)
from renderworld.planning.pose_warp import default_grid, history_poses
from renderworld.world import WorldModelConfig, warp_along_poses
from renderworld.world.pose import PoseWarpWorldModel
from tests.world.fake_tokenizer import PatchTokenizer, PatchTokenizerConfig

register_tokenizer("test_patch", PatchTokenizer)


GRID = (16, 16, 4)
H, S = 5, 6


class CountingTokenizer(PatchTokenizer):
    """Counts the frames it encodes and decodes."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.encoded = self.decoded = 0

    def encode(self, occ):
        self.encoded += occ.shape[0]
        return super().encode(occ)

    def decode(self, tokens):
        self.decoded += tokens.indices.shape[0]
        return super().decode(tokens)


register_tokenizer("test_counting_patch", CountingTokenizer)


def make_model(seed=0, anchors="ctr_cv"):
    torch.manual_seed(seed)
    tok = CountingTokenizer(PatchTokenizerConfig(GRID, patch=2, num_codebooks=2))
    cfg = WorldModelConfig(
        codebook_sizes=tok.codebook_sizes, token_grid=tok.token_grid, embed_dim=16,
        num_heads=2, num_scales=2, layers_per_scale=(1, 1),
    )  # fmt: skip
    wm = PoseWarpWorldModel(cfg, anchors=anchors)
    with torch.no_grad():  # a pose head that is not its anchor, a token net that is not the warp
        for p in wm.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return tok, wm


def make_planner(seed=0, **kw):
    tok, wm = make_model(seed)
    return Planner(tok, wm, **kw)


def scene(t, seed=0):
    """A road with scattered objects, seen from a car driving ~4 m per step and turning left."""
    rng = np.random.default_rng(seed)
    occ = np.full((t, *GRID), FREE_ID, dtype=np.uint8)
    occ[..., 0] = rng.choice([11, 13, 14], size=(t, *GRID[:2]), p=[0.6, 0.2, 0.2])
    occ[:, :, :, 1] = np.where(rng.random((t, *GRID[:2])) < 0.15, rng.integers(1, 11), FREE_ID)
    yaws = np.linspace(-0.08 * (t - 1), 0.0, t)
    xy = np.stack([-4.0 * np.arange(t - 1, -1, -1), 0.3 * np.arange(t - 1, -1, -1) ** 1.5], 1)
    return occ, np.diff(xy, axis=0), yaws


def request(t=H, seed=0, command="left"):
    occ, disp, yaws = scene(t, seed)
    return PlanRequest(occ, disp, command, ego_yaws=yaws)


def test_plan_is_the_models_poses_and_forecast():
    """Trajectory = the pose head's positions; forecast = warp on the grid, token fill off it."""
    planner = make_planner()
    req = request()
    res = planner.plan(req)
    assert res.trajectory.shape == (S, 2) and res.trajectory.dtype == np.float32
    assert res.occupancy_forecast.shape == (S, *GRID) and res.occupancy_forecast.dtype == np.uint8
    # Oracle: the model's own pose head on poses built by hand.
    xy = np.zeros((H, 2))
    for j in range(H - 2, -1, -1):
        xy[j] = xy[j + 1] - req.ego_displacements[j]
    hist = torch.tensor(np.column_stack([xy, req.ego_yaws]), dtype=torch.float32)[None]
    occ = torch.from_numpy(req.occupancy)
    cmd = torch.tensor([COMMANDS.index("left")])
    with torch.no_grad():
        poses, _ = planner.world_model.predict_poses(hist, cmd, occ[None, -1])
    np.testing.assert_array_equal(res.trajectory, poses[0, :, :2].numpy())
    # Where the warp's source lies on the grid the forecast is the warp itself.
    warped = warp_along_poses(occ[-1], poses[0].double(), default_grid(GRID)).numpy()
    inside = warp_along_poses(np.ones((*GRID[:2], 1), np.uint8), poses[0].double(),
                              default_grid((*GRID[:2], 1)), fill=0)[..., 0]  # fmt: skip
    assert 0 < inside.mean() < 1  # the car moves: some space is newly revealed
    on = inside.astype(bool)
    np.testing.assert_array_equal(res.occupancy_forecast[on], warped[on])
    # Elsewhere: classes of the current frame only (the token net's fill), or free.
    assert set(np.unique(res.occupancy_forecast[~on])) <= set(np.unique(req.occupancy[-1]))


def test_history_poses_sum_displacements_back_from_the_current_frame():
    d = np.array([[[4.0, 0.5], [3.0, -0.5]]])
    p = history_poses(d, np.array([[0.2, 0.1, 0.0]]))
    np.testing.assert_allclose(p[0].numpy(), [[-7.0, 0.0, 0.2], [-3.0, 0.5, 0.1], [0, 0, 0]])


def test_trajectory_only_runs_the_pose_head_alone():
    planner = make_planner()
    tok = planner.tokenizer
    req = request()
    full = planner.plan(req)
    before = (tok.encoded, tok.decoded)
    traj = planner.plan(req, forecast=False)
    assert (tok.encoded, tok.decoded) == before  # no encode, no decode
    assert traj.occupancy_forecast is None and traj.timings["encode"] == 0
    np.testing.assert_array_equal(traj.trajectory, full.trajectory)
    # A full plan encodes the H-1 aligned history frames and the S warped frames, decodes S.
    tok.encoded = tok.decoded = 0
    planner.plan(req)
    assert (tok.encoded, tok.decoded) == (H - 1 + S, S)


def test_plan_depends_only_on_the_last_history_frames_and_the_command():
    planner = make_planner()
    occ, disp, yaws = scene(8, seed=1)
    long = PlanRequest(occ, disp, "left", ego_yaws=yaws)
    short = PlanRequest(occ[-H:], disp[-(H - 1) :], "left", ego_yaws=yaws[-H:])
    a, b = planner.plan(long), planner.plan(short)
    np.testing.assert_array_equal(a.trajectory, b.trajectory)
    np.testing.assert_array_equal(a.occupancy_forecast, b.occupancy_forecast)
    # Older frames than the model reads change nothing.
    occ2, disp2, yaws2 = occ.copy(), disp.copy(), yaws.copy()
    occ2[:3] = np.random.default_rng(9).integers(0, FREE_ID + 1, occ2[:3].shape, dtype=np.uint8)
    disp2[:3] = [[1.0, 2.0]] * 3
    yaws2[:3] = 0.7
    c = planner.plan(PlanRequest(occ2, disp2, "left", ego_yaws=yaws2))
    np.testing.assert_array_equal(a.trajectory, c.trajectory)
    np.testing.assert_array_equal(a.occupancy_forecast, c.occupancy_forecast)
    # ... and every input the model reads does change the plan (the test above can fail).
    seen = []  # the token network's logits of each plan
    planner.world_model.net.register_forward_hook(lambda m, i, out: seen.append(out.logits[0]))
    a = planner.plan(long)
    for edit in ("command", "yaw", "displacement", "older frame", "current frame"):
        o, d, y, cmd = occ.copy(), disp.copy(), yaws.copy(), "left"
        if edit == "command":
            cmd = "right"
        elif edit == "yaw":
            y[-2] -= 0.2
        elif edit == "displacement":
            d[-1] *= 1.5
        elif edit == "older frame":
            o[-4] = np.roll(o[-4], 3, axis=0)
            o[-4, ..., 0] = 13
        else:
            o[-1] = np.roll(o[-1], 3, axis=1)
        e = planner.plan(PlanRequest(o, d, cmd, ego_yaws=y))
        assert not torch.equal(seen[-1], seen[0]), edit
        if edit == "older frame":  # read by the token network only (the fill off the grid)
            np.testing.assert_array_equal(e.trajectory, a.trajectory)
        else:
            assert not np.array_equal(e.trajectory, a.trajectory), edit
            assert not np.array_equal(e.occupancy_forecast, a.occupancy_forecast), edit


def test_inputs_are_not_modified():
    planner = make_planner()
    req = request(t=7)
    keep = copy.deepcopy(req)
    planner.plan(req)
    for name in ("occupancy", "ego_displacements", "ego_yaws"):
        np.testing.assert_array_equal(getattr(req, name), getattr(keep, name))


@pytest.mark.parametrize("forecast", [True, False])
def test_session_equals_replanning_from_scratch(forecast):
    planner = make_planner()
    occ, disp, yaws = scene(10, seed=2)
    session = PlannerSession(planner)
    for t in range(10):
        cmd = COMMANDS[t % 3]
        out = session.step(occ[t], disp[:t], cmd, forecast, ego_yaws=yaws[: t + 1] - yaws[t])
        if t < H - 1:
            assert out is None
            continue
        ref = planner.plan(
            PlanRequest(occ[: t + 1], disp[:t], cmd, ego_yaws=yaws[: t + 1] - yaws[t]), forecast
        )
        np.testing.assert_array_equal(out.trajectory, ref.trajectory)
        if forecast:
            np.testing.assert_array_equal(out.occupancy_forecast, ref.occupancy_forecast)
        else:
            assert out.occupancy_forecast is None


def test_batch_equals_single_plans():
    planner = make_planner()
    reqs = [request(seed=s, command=c) for s, c in ((0, "left"), (1, "straight"), (2, "right"))]
    batch = planner.plan_batch(reqs)
    for req, res in zip(reqs, batch, strict=True):
        one = planner.plan(req)
        np.testing.assert_allclose(res.trajectory, one.trajectory, rtol=0, atol=1e-5)
        agree = (res.occupancy_forecast == one.occupancy_forecast).mean()
        assert agree >= 0.999


def test_missing_or_bad_yaws_are_refused():
    planner = make_planner()
    occ, disp, yaws = scene(H)
    with pytest.raises(ValueError, match=r"requests\[0\]\.ego_yaws: the pose-warp world model"):
        planner.plan(PlanRequest(occ, disp, "left"))
    for bad, msg in (
        (yaws[:-1], r"ego_yaws: expected shape \[T\] = \[5\]"),
        (yaws + 0.1, "ego_yaws: expected 0 for the current frame"),
        (np.where(np.arange(H) == 0, np.nan, yaws), "ego_yaws: expected finite"),
        (np.where(np.arange(H) == 0, 4.0, yaws), r"ego_yaws: expected radians in \[-pi, pi\]"),
        (np.zeros(H, dtype=np.int64), "ego_yaws: expected a float dtype"),
    ):
        with pytest.raises(ValueError, match=msg):
            PlanRequest(occ, disp, "left", ego_yaws=bad)
    session = PlannerSession(planner)
    for frame in occ:
        session.push(frame)
    with pytest.raises(ValueError, match="ego_yaws: the pose-warp world model needs"):
        session.plan(disp, "left")
    with pytest.raises(ValueError, match="ego_yaws: expected 0 for the current frame"):
        session.plan(disp, "left", ego_yaws=yaws + 0.1)
    with pytest.raises(ValueError, match=r"occupancy: expected the planner's grid \(16, 16, 4\)"):
        PlannerSession(planner).push(np.full((8, 8, 4), FREE_ID, np.uint8))


def test_token_planner_ignores_yaws():
    from tests.planning.test_api import make_planner as token_planner
    from tests.planning.test_api import make_request

    planner = token_planner()
    req = make_request()
    a = planner.plan(req)
    b = planner.plan(PlanRequest(req.occupancy, req.ego_displacements, req.command,
                                 ego_yaws=np.linspace(-0.3, 0.0, 5)))  # fmt: skip
    np.testing.assert_array_equal(a.trajectory, b.trajectory)
    np.testing.assert_array_equal(a.occupancy_forecast, b.occupancy_forecast)


def test_grid_checks():
    tok, wm = make_model()
    with pytest.raises(ValueError, match=r"grid: expected the tokenizer's grid_shape"):
        Planner(tok, wm, grid=GridSpec("g", (-40, -40, -1), (40, 40, 5.4), (8, 8, 4)))
    with pytest.raises(TypeError, match="grid: expected a GridSpec or None"):
        Planner(tok, wm, grid=(16, 16, 4))
    with pytest.raises(TypeError, match="world_model: expected WorldModel or PoseWarpWorldModel"):
        Planner(tok, wm.pose)


def test_bundle_round_trip_keeps_kind_anchors_and_grid(tmp_path):
    tok, wm = make_model(seed=4, anchors="ctr")
    grid = GridSpec("narrow", (-20.0, -20.0, -1.0), (20.0, 20.0, 5.4), GRID)
    planner = Planner(tok, wm, grid=grid)
    path = save_planner_bundle(tmp_path / "p.pt", tok, wm, grid=grid)
    data = torch.load(path, weights_only=True)
    assert data["schema_version"] == 2 and data["world_model"]["kind"] == "pose_warp"
    assert data["world_model"]["options"]["anchors"] == "ctr"
    loaded = load_planner(path)
    assert loaded.kind == "pose_warp" and loaded.grid == grid
    assert loaded.world_model.pose.anchors == "ctr"
    req = request(seed=3)
    a, b = planner.plan(req), loaded.plan(req)
    np.testing.assert_array_equal(a.trajectory, b.trajectory)
    np.testing.assert_array_equal(a.occupancy_forecast, b.occupancy_forecast)
    # The grid matters: the default (Occ3D range) grid warps by other voxel sizes.
    other = Planner(tok, wm).plan(req)
    assert not np.array_equal(other.occupancy_forecast, a.occupancy_forecast)


def _tampered(tmp_path, edit):
    tok, wm = make_model()
    path = save_planner_bundle(tmp_path / "b.pt", tok, wm)
    data = torch.load(path, weights_only=True)
    edit(data)
    torch.save(data, path)
    return path


@pytest.mark.parametrize(
    ("edit", "msg"),
    [
        (lambda d: d["world_model"].update(kind="diffusion"), "world_model kind: expected one of"),
        (lambda d: d["world_model"]["options"].update(anchors="cv"), "anchors: expected one of"),
        (lambda d: d["world_model"]["options"].update(movers="flow"), "movers: expected one of"),
        (lambda d: d["world_model"]["options"].pop("grid"), "world_model options: expected keys"),
        (lambda d: d["world_model"]["options"]["grid"].update(shape=[8, 8, 4]),
         r"grid shape \(8, 8, 4\) does not match the tokenizer's grid_shape"),
        (lambda d: d["world_model"]["options"]["grid"].update(range_max=[-50, 40, 5]),
         "expected range_min < range_max"),
        (lambda d: d["world_model"].update(kind="tokens"), "world_model options: expected keys"),
        (lambda d: d["world_model"].pop("kind"), "world_model: expected keys"),
    ],
)  # fmt: skip
def test_tampered_pose_warp_bundles_are_refused(tmp_path, edit, msg):
    path = _tampered(tmp_path, edit)
    with pytest.raises(ValueError, match=msg) as err:
        load_planner(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("movers", ["static", "object_cv"])
def test_bundles_keep_how_the_forecast_moves_others(tmp_path, movers):
    tok, wm = make_model(seed=5)
    wm.movers = movers
    path = save_planner_bundle(tmp_path / "m.pt", tok, wm)
    assert torch.load(path, weights_only=True)["world_model"]["options"]["movers"] == movers
    assert load_planner(path).world_model.movers == movers
    # A bundle written before the option existed (no "movers") loads as a static world.
    old = _tampered(tmp_path, lambda d: d["world_model"]["options"].pop("movers"))
    assert load_planner(old).world_model.movers == "static"


def test_bundles_keep_a_pose_head_that_reads_kinematics(tmp_path):
    torch.manual_seed(3)
    tok, base = make_model(seed=3)
    wm = PoseWarpWorldModel(base.config, anchors="ctr_cv", kinematics=True)
    with torch.no_grad():
        for p in wm.parameters():
            p.add_(0.05 * torch.randn_like(p))
    path = save_planner_bundle(tmp_path / "k.pt", tok, wm)
    assert torch.load(path, weights_only=True)["world_model"]["options"]["kinematics"] is True
    loaded = load_planner(path).world_model
    assert loaded.pose.kinematics
    req = request()
    np.testing.assert_array_equal(
        Planner(tok, wm).plan(req).trajectory, load_planner(path).plan(req).trajectory
    )
    # Written before the option existed (no "kinematics"): a head without them.
    old = _tampered(tmp_path, lambda d: d["world_model"]["options"].pop("kinematics"))
    assert load_planner(old).world_model.pose.kinematics is False
    bad = _tampered(tmp_path, lambda d: d["world_model"]["options"].update(kinematics="yes"))
    with pytest.raises(ValueError, match="kinematics: expected true or false"):
        load_planner(bad)


def _round_trip(tmp_path, name, **options):
    """A perturbed pose-warp model with ``options``, bundled and loaded again; its plan and the
    loaded one's must agree. Returns (the bundle's path, the loaded planner, the request)."""
    tok, base = make_model(seed=4)
    wm = PoseWarpWorldModel(base.config, anchors="ctr_cv", **options)
    with torch.no_grad():
        for p in wm.parameters():
            p.add_(0.05 * torch.randn_like(p))
    path = save_planner_bundle(tmp_path / name, tok, wm)
    loaded = load_planner(path)
    req = request()
    np.testing.assert_array_equal(
        Planner(tok, wm).plan(req).trajectory, loaded.plan(req).trajectory
    )
    return path, loaded, req


def test_bundles_keep_a_pose_head_that_reads_motion(tmp_path):
    path, loaded, req = _round_trip(tmp_path, "m.pt", motion_frames=2)
    assert torch.load(path, weights_only=True)["world_model"]["options"]["motion_frames"] == 2
    assert loaded.world_model.pose.motion_frames == 2
    # The plan reads the past frames: moving the past objects changes it.
    other = PlanRequest(req.occupancy.copy(), req.ego_displacements, req.command, req.ego_yaws)
    other.occupancy[:-1, :, :, 1] = FREE_ID
    assert not np.array_equal(loaded.plan(other).trajectory, loaded.plan(req).trajectory)
    # Written before the option existed (no "motion_frames"): a head without it.
    old = _tampered(tmp_path, lambda d: d["world_model"]["options"].pop("motion_frames"))
    assert load_planner(old).world_model.pose.motion_frames == 0
    bad = _tampered(tmp_path, lambda d: d["world_model"]["options"].update(motion_frames=-1))
    with pytest.raises(ValueError, match="motion_frames: expected an int >= 0"):
        load_planner(bad)


def test_bundles_keep_pose_heads_that_read_the_agents(tmp_path):
    tok, base = make_model(seed=4)
    wm = PoseWarpWorldModel(base.config, anchors="ctr_cv", agents=3, pose_heads=2)
    with torch.no_grad():
        for p in wm.parameters():
            p.add_(0.05 * torch.randn_like(p))
    path = save_planner_bundle(tmp_path / "a.pt", tok, wm)
    options = torch.load(path, weights_only=True)["world_model"]["options"]
    assert options["agents"] == 3 and options["pose_heads"] == 2
    loaded = load_planner(path)
    assert loaded.world_model.pose.agents == 3 and len(loaded.world_model.pose.members) == 2
    req = request()
    np.testing.assert_array_equal(
        Planner(tok, wm).plan(req).trajectory, loaded.plan(req).trajectory
    )

    # Written before the options existed: one head without agents.
    def pop(d):
        for key in ("agents", "pose_heads"):
            d["world_model"]["options"].pop(key)

    old = load_planner(_tampered(tmp_path, pop)).world_model.pose
    assert old.agents == 0 and not hasattr(old, "members")
    bad = _tampered(tmp_path, lambda d: d["world_model"]["options"].update(agents=True))
    with pytest.raises(ValueError, match="agents: expected an int >= 0"):
        load_planner(bad)
    bad = _tampered(tmp_path, lambda d: d["world_model"]["options"].update(pose_heads=0))
    with pytest.raises(ValueError, match="pose_heads: expected an int >= 1"):
        load_planner(bad)


def test_schema_1_token_bundles_still_load(tmp_path):
    from tests.planning.test_api import make_planner as token_planner
    from tests.planning.test_api import make_request

    planner = token_planner()
    path = save_planner_bundle(tmp_path / "v2.pt", planner.tokenizer, planner.world_model)
    data = torch.load(path, weights_only=True)
    assert data["world_model"]["kind"] == "tokens" and data["world_model"]["options"] == {}
    data["schema_version"] = 1
    for key in ("kind", "options"):
        del data["world_model"][key]
    torch.save(data, tmp_path / "v1.pt")
    loaded = load_planner(tmp_path / "v1.pt")
    assert loaded.kind == "tokens"
    req = make_request()
    np.testing.assert_array_equal(loaded.plan(req).trajectory, planner.plan(req).trajectory)


def test_retain_freed_memory_checks_its_arguments():
    import ctypes.util

    from renderworld.planning import retain_freed_memory

    with pytest.raises(ValueError, match="mmap_threshold: expected a positive int"):
        retain_freed_memory(mmap_threshold=0)
    with pytest.raises(ValueError, match="trim_threshold: expected a positive int"):
        retain_freed_memory(trim_threshold=1.5)
    with pytest.raises(ValueError, match="mmap_threshold: expected at most 33554432 bytes"):
        retain_freed_memory(mmap_threshold=2**30)
    glibc = "libc.so" in str(ctypes.util.find_library("c"))
    assert retain_freed_memory() is glibc


@pytest.mark.parametrize("kind", ["tokens", "pose_warp"])
def test_world_model_threads_are_used_and_restored(kind):
    from tests.planning.test_api import make_planner as token_planner
    from tests.planning.test_api import make_request

    ref = token_planner() if kind == "tokens" else make_planner()
    req = make_request() if kind == "tokens" else request()
    seen = []
    planner = Planner(ref.tokenizer, ref.world_model, world_model_threads=2)
    net = planner.world_model if kind == "tokens" else planner.world_model.net
    net.register_forward_pre_hook(lambda *_: seen.append(torch.get_num_threads()))
    before = torch.get_num_threads()  # 1 in these tests (conftest)
    res = planner.plan(req)
    assert seen and set(seen) == {2} and torch.get_num_threads() == before
    want = ref.plan(req)
    np.testing.assert_allclose(res.trajectory, want.trajectory, rtol=0, atol=1e-5)
    assert (res.occupancy_forecast == want.occupancy_forecast).mean() >= 0.999
    for bad in (0, 1.0, "2"):
        with pytest.raises(ValueError, match="world_model_threads: expected None or an int >= 1"):
            Planner(ref.tokenizer, ref.world_model, world_model_threads=bad)


@pytest.mark.parametrize("forecast", [False, True])
def test_checked_plan_through_the_api_and_the_session(forecast):
    from renderworld.planning.check import CandidateScores

    planner = make_planner()
    occ, disp, yaws = scene(H)
    req = PlanRequest(occ, disp, "left", ego_yaws=yaws)
    raw = planner.plan(req, forecast=forecast)
    checked = planner.plan(req, forecast=forecast, check=True)
    assert raw.raw_trajectory is None and raw.candidates is None
    np.testing.assert_array_equal(checked.raw_trajectory, raw.trajectory)
    assert isinstance(checked.candidates, CandidateScores)
    best = checked.candidates.best
    np.testing.assert_allclose(checked.trajectory, checked.candidates.waypoints[best], atol=1e-6)
    np.testing.assert_array_equal(checked.yaws, raw.yaws)  # the forecast's frames: the model's
    if forecast:
        np.testing.assert_array_equal(checked.occupancy_forecast, raw.occupancy_forecast)
    assert checked.timings["check"] > 0 and "check_scoring" in checked.timings
    session = PlannerSession(planner)
    for frame in occ:
        session.push(frame)
    streamed = session.plan(disp, "left", forecast=forecast, ego_yaws=yaws, check=True)
    np.testing.assert_array_equal(streamed.trajectory, checked.trajectory)


def test_the_session_checks_against_the_mover_forecast_it_is_given():
    planner = make_planner()
    occ, disp, yaws = scene(H)
    seen = []

    def movers(tracks, current, history_poses, grid, steps, dt):
        seen.append(len(tracks))
        return np.zeros((len(tracks), steps + 1, 2))

    session = PlannerSession(planner)
    for frame in occ:
        session.push(frame)
    session.plan(disp, "left", forecast=False, ego_yaws=yaws, check=True, movers=movers)
    assert len(seen) == 1 and seen[0] >= 1  # read once, with the scene's movers
    with pytest.raises(ValueError, match="movers: only the check reads"):
        session.plan(disp, "left", forecast=False, ego_yaws=yaws, movers=movers)


def test_a_token_planner_refuses_to_check():
    from tests.planning.test_api import make_planner as token_planner
    from tests.planning.test_api import make_request

    planner = token_planner()
    with pytest.raises(ValueError, match="check: checking a plan against the forecast needs"):
        planner.plan(make_request(), check=True)
    with pytest.raises(TypeError, match="check: expected a bool"):
        planner.plan(make_request(), check=1)


def test_bundles_keep_a_finer_bird_s_eye_readout(tmp_path):
    path, loaded, _ = _round_trip(tmp_path, "p.pt", bev_pool=7)
    assert torch.load(path, weights_only=True)["world_model"]["options"]["bev_pool"] == 7
    assert loaded.world_model.pose.bev_pool == 7
    # Written before the option existed: the 4 x 4 readout.
    old = _tampered(tmp_path, lambda d: d["world_model"]["options"].pop("bev_pool"))
    assert load_planner(old).world_model.pose.bev_pool == 4
    bad = _tampered(tmp_path, lambda d: d["world_model"]["options"].update(bev_pool=0))
    with pytest.raises(ValueError, match="bev_pool: expected an int >= 1"):
        load_planner(bad)


def test_bundles_keep_a_pose_head_that_reads_its_leader(tmp_path):
    path, loaded, _ = _round_trip(tmp_path, "l.pt", leader=True)
    assert torch.load(path, weights_only=True)["world_model"]["options"]["leader"] is True
    assert loaded.world_model.pose.leader
    # Written before the option existed: a head without it.
    old = _tampered(tmp_path, lambda d: d["world_model"]["options"].pop("leader"))
    assert not load_planner(old).world_model.pose.leader
    bad = _tampered(tmp_path, lambda d: d["world_model"]["options"].update(leader="yes"))
    with pytest.raises(ValueError, match="leader: expected true or false"):
        load_planner(bad)


def test_bundles_keep_the_stop_behind_a_braking_leader(tmp_path):
    path, loaded, _ = _round_trip(tmp_path, "s.pt", leader_stop=True)
    assert torch.load(path, weights_only=True)["world_model"]["options"]["leader_stop"] is True
    assert loaded.world_model.leader_stop and not loaded.world_model.training
    old = _tampered(tmp_path, lambda d: d["world_model"]["options"].pop("leader_stop"))
    assert not load_planner(old).world_model.leader_stop
    bad = _tampered(tmp_path, lambda d: d["world_model"]["options"].update(leader_stop=1))
    with pytest.raises(ValueError, match="leader_stop: expected true or false"):
        load_planner(bad)
